"""What the command line promises a user: a sealed run stays sealed, no command loses a user's files,
bad input gets a one-line error, and an interrupted run resumes exactly (SIGINT and SIGKILL)."""
import json
import os
import signal
import stat
import subprocess
import sys
import time

import pytest
import torch

from securegs_warp.cli import main
from securegs_warp.keys import SEALED_MAGIC

TINY = ["--width", "24", "--height", "18", "--train-views", "3", "--test-views", "1"]


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("error: "), err
    assert "Traceback" not in "\n".join(err)
    return err[-1]


# --- secrets -------------------------------------------------------------------------------------

def test_a_sealed_run_writes_nothing_private_in_plain(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PASS", "correct horse")
    out = tmp_path / "sealed"
    args = ["hide", "--out", str(out), "--iterations", "4", "--quiet", "--payload", "object+bits:0b10110011",
            "--passphrase-env", "PASS", *TINY]
    assert main(args) == 0
    assert (out / "key.sealed").read_bytes().startswith(SEALED_MAGIC)
    assert (out / "checkpoint.pt").read_bytes().startswith(SEALED_MAGIC)  # it holds the private heads
    metrics = (out / "metrics.json").read_text()
    assert "bits" not in json.loads(metrics)
    for name in ("metrics.json", "config.json", "log.jsonl"):  # the literal message is in no plain file
        assert "10110011" not in (out / name).read_text(), name
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    for path in out.rglob("*"):
        assert stat.S_IMODE(path.stat().st_mode) & 0o077 == 0, path  # nothing readable by others

    # Resuming without the passphrase is refused: no plain key or checkpoint is written.
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    monkeypatch.delenv("PASS")
    assert main(["hide", "--out", str(out), "--iterations", "4", "--quiet", "--payload", "object+bits:0b10110011",
                 "--resume", *TINY]) == 2
    message = _error(capsys)
    assert "sealed" in message and "--passphrase-env" in message
    assert not (out / "key.safetensors").exists()
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_random_bits_are_not_derived_from_the_recorded_seed(tmp_path):
    """config.json records the seed: a message drawn from it could be recomputed by anyone who reads
    the run folder. Two runs with the same seed hide different messages."""
    from securegs_warp.config import SecureConfig, TrainConfig
    from securegs_warp.data import make_synthetic_scene
    from securegs_warp.rasterizer import RasterOptions
    from securegs_warp.secure import SecureTrainer

    scene = make_synthetic_scene(width=24, height=18, n_train=3, n_test=1, n_points=200)
    config = TrainConfig(iterations=2, raster=RasterOptions(tile_size=8))
    messages = {tuple(SecureTrainer(scene, config, SecureConfig(payload="bits:64")).payload.bits.tolist())
                for _ in range(2)}
    assert len(messages) == 2


def test_a_warning_of_the_package_is_one_line(tmp_path, capsys):
    """A person at a terminal reads the package's own warnings as ``warning: ...``, without Python's
    file and source line: here, bits that no anchor carries in a grid far too coarse for 256 bits."""
    assert main(["hide", "--out", str(tmp_path / "r"), "--payload", "bits:256", "--bit-cell", "64",
                 "--iterations", "2", "--quiet", *TINY]) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "no occupied cell" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "--bit-cell" in lines[0]
    assert "UserWarning" not in err and "trainer.py" not in err


def test_a_literal_message_resumes_by_its_length_and_refuses_another(tmp_path, capsys):
    # config.json and the checkpoint record a literal message by its length: resuming takes either
    # the length or the same literal; another literal would silently change the secret, and is refused.
    out = tmp_path / "run"
    args = ["hide", "--out", str(out), "--iterations", "4", "--checkpoint-every", "2", "--quiet", *TINY]
    assert main(args + ["--payload", "bits:0b1011"]) == 0
    assert '"bits:4"' in (out / "config.json").read_text()
    for payload in ("bits:4", "bits:0b1011"):
        assert main(args + ["--payload", payload, "--resume"]) == 0, payload
    assert main(args + ["--payload", "bits:0b0000", "--resume"]) == 2
    assert "another message" in _error(capsys)
    assert json.loads((out / "metrics.json").read_text())["bit_accuracy"] == 1.0


# --- files ---------------------------------------------------------------------------------------

def test_out_that_is_not_a_run_is_never_touched(tmp_path, capsys):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "thesis.tex").write_text("years of work")
    for force in ([], ["--force"]):
        assert main(["train", "--out", str(folder), "--iterations", "2", "--quiet", *TINY, *force]) == 2
        assert "not a securegs run" in _error(capsys)
    assert sorted(p.name for p in folder.iterdir()) == ["thesis.tex"]
    assert (folder / "thesis.tex").read_text() == "years of work"
    a_file = tmp_path / "file"
    a_file.write_text("x")
    assert main(["train", "--out", str(a_file), "--iterations", "2", "--quiet", *TINY]) == 2
    assert "is a file" in _error(capsys)


def test_force_replaces_only_what_a_run_wrote(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--out", str(out), "--iterations", "2", "--quiet", *TINY]
    assert main(args) == 0
    (out / "renders" / "stale_view.png").write_bytes(b"old")
    (out / "notes.txt").write_text("mine")
    assert main(args) == 2  # a run is there: neither --resume nor --force
    assert "already holds a run" in _error(capsys)
    assert main(args + ["--force"]) == 0
    assert not (out / "renders" / "stale_view.png").exists()  # renders/ is ours: rewritten whole
    assert (out / "notes.txt").read_text() == "mine"  # not ours: kept


def test_force_keeps_the_earlier_run_when_the_new_inputs_fail(tmp_path, capsys):
    # The earlier run (its key included) is cleared only once the new scene has loaded.
    out = tmp_path / "run"
    args = ["hide", "--out", str(out), "--iterations", "2", "--quiet", *TINY]
    assert main(args) == 0
    key = (out / "key.safetensors").read_bytes()
    for wrong, named in ((["--hide", str(tmp_path / "missing.obj")], "missing.obj"),
                         (["--scene", str(tmp_path / "no_scene")], "no_scene")):
        assert main(args + ["--force", *wrong]) == 2
        assert named in _error(capsys)
        assert (out / "key.safetensors").read_bytes() == key and (out / "public").is_dir()


def test_resume_without_a_checkpoint_says_so(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--out", str(out), "--iterations", "2", "--quiet", *TINY]
    assert main(args) == 0
    (out / "checkpoint.pt").unlink()  # as a run stopped before its first checkpoint has none
    assert main(args + ["--resume"]) == 2
    assert "no checkpoint to resume from" in _error(capsys)


def test_demo_on_an_existing_run_needs_force(tmp_path, capsys, monkeypatch):
    import securegs_warp.cli.secure as secure_cli

    out = tmp_path / "demo"
    real = secure_cli.cmd_hide

    def small_hide(args):  # the demo's own budget, on a tiny scene
        for name, value in (("scene.width", "24"), ("scene.height", "18"), ("scene.n_train", "3"),
                            ("scene.n_test", "1"), ("train.iterations", "2")):
            setattr(args, name, value)
        return real(args)

    monkeypatch.setattr(secure_cli, "cmd_hide", small_hide)
    assert main(["demo", "--out", str(out), "--quiet"]) == 0
    assert main(["demo", "--out", str(out), "--quiet"]) == 2
    assert "--force" in _error(capsys)
    assert main(["demo", "--out", str(out), "--quiet", "--force"]) == 0


def test_reveal_out_refuses_used_folders(tmp_path, capsys):
    run, out = tmp_path / "c", tmp_path / "revealed"
    assert main(["hide", "--out", str(run), "--iterations", "2", "--quiet", "--payload", "bits:8", *TINY]) == 0
    reveal = ["reveal", str(run / "public"), "--key", str(run / "key.safetensors"), "--out", str(out)]
    assert main(reveal) == 0
    assert main(reveal) == 2
    assert "--force" in _error(capsys)
    assert main(reveal + ["--force"]) == 0
    # what a reveal writes is the secret: its owner's only
    assert stat.S_IMODE((out / "bits.json").stat().st_mode) == 0o600
    # without a key reveal needs --scene: refused before the earlier reveal is replaced
    assert main(["reveal", str(run / "public"), "--out", str(out), "--force"]) == 2
    assert "needs --scene" in _error(capsys) and (out / "bits.json").is_file()
    (out / "thesis.tex").write_text("mine")
    assert main(reveal + ["--force"]) == 2
    assert "other files" in _error(capsys)
    assert (out / "thesis.tex").read_text() == "mine"


def test_disk_full_is_one_line_and_loses_nothing(tmp_path, monkeypatch, capsys):
    """The disk fills up as the finished run writes its metrics: one line, the checkpoint of the
    last step is intact, and once there is room again --resume finishes the run without training."""
    import errno

    import securegs_warp.io.atomic as atomic

    out = tmp_path / "run"
    args = ["train", "--out", str(out), "--iterations", "3", "--quiet", *TINY]
    real = atomic.atomic_open

    def full(path):
        if str(path).endswith("metrics.json"):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path)

    monkeypatch.setattr(atomic, "atomic_open", full)
    assert main(args) == 2
    assert "No space left on device" in _error(capsys)
    assert not (out / "metrics.json").exists() and not list(out.glob(".*.tmp"))
    monkeypatch.setattr(atomic, "atomic_open", real)
    assert main(args + ["--resume"]) == 0
    assert json.loads((out / "metrics.json").read_text())["psnr"] > 0
    assert json.loads((out / "log.jsonl").read_text().splitlines()[-1])["step"] == 3  # no step trained twice


# --- bad input -----------------------------------------------------------------------------------

# (extra arguments, what the one-line error says), by where the check lives
CONFIG_FIELDS = [(["--iterations", "0"], "iterations must be >= 1"), (["--iterations", "-5"], "iterations must be >= 1"),
                 (["--iterations", "ten"], "not a valid int"), (["--tile-size", "12"], "tile_size must be 8, 16 or 32"),
                 (["--seed", str(2**70)], "seed must fit a signed 64-bit integer")]
SCENE_FIELDS = [(["--width", "0"], "width must be >= 1"), (["--height", "-1"], "height must be >= 1"),
                (["--train-views", "0"], "n_train must be >= 1"), (["--test-views", "0"], "n_test"),
                (["--downscale", "0"], "downscale must be >= 1")]
RUN_OPTIONS = [(["--log-every", "0"], "--log-every must be >= 1"),
               (["--checkpoint-every", "0"], "--checkpoint-every must be >= 1"),
               (["--device", "bogus"], "--device"), (["--device", "mps"], "only cpu and cuda")]


@pytest.mark.parametrize("extra, message", CONFIG_FIELDS + SCENE_FIELDS + RUN_OPTIONS)
def test_bad_options_get_one_line(tmp_path, capsys, extra, message):
    out = tmp_path / "r"
    assert main(["train", "--out", str(out), "--quiet", *TINY, *extra]) == 2
    assert message in _error(capsys)
    assert not out.exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_cuda_without_cuda_is_refused(tmp_path, capsys):
    assert main(["train", "--out", str(tmp_path / "r"), "--device", "cuda", "--quiet", *TINY]) == 2
    assert "no usable CUDA" in _error(capsys)


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 truncated zip", b"\x80\x04\x95 not a checkpoint"])
def test_damaged_checkpoint_on_resume_is_one_line(tmp_path, capsys, content):
    out = tmp_path / "r"
    args = ["train", "--out", str(out), "--iterations", "3", "--quiet", *TINY]
    assert main(args) == 0
    (out / "checkpoint.pt").write_bytes(content)
    assert main(args + ["--resume"]) == 2
    assert "checkpoint" in _error(capsys)


def test_malicious_checkpoint_is_refused_without_running_it(tmp_path, capsys):
    out = tmp_path / "r"
    args = ["train", "--out", str(out), "--iterations", "3", "--quiet", *TINY]
    assert main(args) == 0
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    torch.save({"step": 1, "payload": Evil()}, out / "checkpoint.pt")
    assert main(args + ["--resume"]) == 2
    assert "checkpoint" in _error(capsys)
    assert not marker.exists()


def test_every_option_has_help_and_there_is_a_version(capsys):
    from securegs_warp.cli import build_parser

    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command").choices
    for name, sub in subparsers.items():
        for action in sub._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, f"securegs {name} {action.option_strings[0]} has no help"
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and "securegs-warp" in capsys.readouterr().out


# --- interrupted runs ----------------------------------------------------------------------------

def _run(args, cwd, **kwargs):
    return subprocess.Popen([sys.executable, "-m", "securegs_warp.cli", *args], cwd=cwd, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, **kwargs)


def _wait_for_step(log, step, proc, timeout=240):
    t0 = time.time()
    while time.time() - t0 < timeout and proc.poll() is None:
        if log.exists():
            lines = log.read_text().splitlines()
            if lines and json.loads(lines[-1])["step"] >= step:
                return
        time.sleep(0.05)
    raise AssertionError(f"the run did not reach step {step}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_interrupted_run_resumes_to_the_same_model(tmp_path, sig):
    """A run stopped by Ctrl-C (SIGINT: checkpoint at the last whole step, exit 130) or killed
    (SIGKILL: the last periodic checkpoint) and resumed ends with the same files as a run that was
    never stopped."""
    common = ["train", "--iterations", "24", "--quiet", "--log-every", "1", "--checkpoint-every", "1", *TINY]
    straight = _run(common + ["--out", "straight"], tmp_path)
    assert straight.wait(timeout=300) == 0, straight.stderr.read().decode()

    proc = _run(common + ["--out", "stopped"], tmp_path)
    _wait_for_step(tmp_path / "stopped" / "log.jsonl", 8, proc)
    proc.send_signal(sig)
    code = proc.wait(timeout=120)
    assert code == (130 if sig == signal.SIGINT else -signal.SIGKILL), proc.stderr.read().decode()
    assert not (tmp_path / "stopped" / "model").exists()
    resumed = _run(common + ["--out", "stopped", "--resume"], tmp_path)
    assert resumed.wait(timeout=300) == 0, resumed.stderr.read().decode()
    for name in sorted(os.listdir(tmp_path / "straight" / "model")):
        a = (tmp_path / "straight" / "model" / name).read_bytes()
        b = (tmp_path / "stopped" / "model" / name).read_bytes()
        assert a == b, name


def test_cpu_training_takes_half_the_cores(tmp_path):
    """Two CPU runs at once must not oversubscribe the machine: each command gives torch half the
    cores it may run on (one on a 2-core machine)."""
    from securegs_warp.cli.common import cpu_threads, resolve_device

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    before = torch.get_num_threads()
    try:
        resolve_device("cpu")
        assert torch.get_num_threads() == cpu_threads() == max(1, cores // 2)
    finally:
        torch.set_num_threads(before)


# --- usability ------------------------------------------------------------------------------------

def test_model_commands_read_hide_runs(tmp_path):
    """render, eval and export load the saved model of a `hide` run (its public/ release) as they do
    a `train` run's model/; export writes every anchor's Gaussians, not one view's visible ones."""
    from securegs_warp.config import SceneSpec
    from securegs_warp.io import read_3dgs_ply
    from securegs_warp.scaffold_model import ScaffoldModel

    run = tmp_path / "c"
    assert main(["hide", "--out", str(run), "--iterations", "2", "--quiet", "--payload", "bits:8", *TINY]) == 0
    assert main(["eval", str(run)]) == 0 and (run / "eval.json").is_file()
    assert main(["render", str(run), "--out", str(tmp_path / "r")]) == 0
    assert main(["export", str(run), "--out", str(tmp_path / "x.ply")]) == 0
    model = ScaffoldModel.load(run / "public")
    cam = SceneSpec(width=24, height=18, n_train=3, n_test=1).load().train[0]
    exported = read_3dgs_ply(tmp_path / "x.ply")["means"].shape[0]
    assert exported == model.gaussians(cam)["means"].shape[0]


def test_relative_scene_folders_are_recorded_absolute(tmp_path, monkeypatch):
    """A data folder given relative to where the run started still loads from anywhere later."""
    from securegs_warp.config import SceneSpec

    (tmp_path / "data").mkdir()
    monkeypatch.chdir(tmp_path)
    assert SceneSpec(source="data").source == str(tmp_path / "data")
    assert SceneSpec(source="synthetic").source == "synthetic"  # a built-in name stays a name


def test_commands_print_no_warp_banner(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "securegs_warp.cli", "train", "--out", str(tmp_path / "r"),
                           "--iterations", "2", "--quiet", *TINY], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    for line in (proc.stdout + proc.stderr).splitlines():
        assert "Warp" not in line and "Module " not in line, line
