"""scripts/hiding_study.py end to end on the CPU at a toy budget: two cases and two variants in the
garden, the table and the AUCs, the anchor-cloud pictures, a rerun that reuses what is done and
resumes what is not, and the settings guard."""
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "hiding_study.py"
PLOTS = importlib.util.find_spec("matplotlib") is not None
TOY = ["--width", "32", "--height", "24", "--iterations", "20", "--attacks", "prune-random", "--draws", "1",
       "--scene", "garden"]


def study(out, *args):
    return subprocess.run([sys.executable, str(SCRIPT), "--case", "mug:stand:0", "--case", "pawn:sink:1", *TOY,
                           "--variant", "default=", "--variant", "rdo=--mode rdo", "--out", str(out), *args],
                          capture_output=True, text=True)


def test_two_cases_give_a_row_each_and_the_aucs_and_a_rerun_reuses_them(tmp_path):
    done = study(tmp_path)
    assert done.returncode == 0, done.stderr + done.stdout
    result = json.loads((tmp_path / "study.json").read_text())
    assert [(r["case"], r["variant"]) for r in result["rows"]] == [
        ("mug_stand_s0", "default"), ("mug_stand_s0", "rdo"), ("pawn_sink_s1", "default"), ("pawn_sink_s1", "rdo")]
    for row in result["rows"]:
        assert row["bits"] is not None and row["hidden"] is not None and row["audit_score"] >= 0
        assert set(row["attacks"]) == {"prune-random:0.2", "prune-random:0.3"}
    # Each variant is its own kind of container: the rdo one trained in the paper's mode.
    assert '"mode": "rdo"' in (tmp_path / "mug_stand_s0" / "hide_rdo" / "config.json").read_text()
    assert '"mode": "cover"' in (tmp_path / "mug_stand_s0" / "hide" / "config.json").read_text()
    for run in ("plain", "hide"):  # --scene reaches both trainings: the cover is the garden
        assert json.loads((tmp_path / "pawn_sink_s1" / run / "config.json").read_text())["scene"]["source"] == "garden"
    # Two covers (seeds 0 and 1): each container against the other's plain model.
    for variant in ("default", "rdo"):
        pair = result["aucs"]["all"][variant]
        assert 0.0 <= pair["without"] <= 1.0 and 0.0 <= pair["with"] <= 1.0
    assert "| mug_stand_s0 | rdo |" in (tmp_path / "study.md").read_text()
    # A sweep counts as done by its marker, written when it ended (its JSON grows attack by attack).
    assert (tmp_path / "mug_stand_s0" / "robustness.done").is_file()
    # The anchor-cloud pictures need the plots extra; without it the study says so and ends well.
    pictures = {case: tmp_path / case / "anchor_clouds.png" for case in ("mug_stand_s0", "pawn_sink_s1")}
    if PLOTS:
        assert all(p.is_file() for p in pictures.values())
        drawn = {case: p.stat().st_mtime_ns for case, p in pictures.items()}
    else:
        assert "no anchor-cloud pictures: matplotlib is not installed" in done.stdout

    plain = tmp_path / "mug_stand_s0" / "plain" / "metrics.json"
    before = plain.stat().st_mtime_ns
    mug_audit = (tmp_path / "mug_stand_s0" / "audit.json").stat().st_mtime_ns
    (tmp_path / "pawn_sink_s1" / "hide" / "metrics.json").unlink()  # as if interrupted at the end
    again = study(tmp_path)
    assert again.returncode == 0, again.stderr + again.stdout
    assert plain.stat().st_mtime_ns == before  # done: not trained again
    assert (tmp_path / "pawn_sink_s1" / "hide" / "metrics.json").is_file()
    assert "resuming" in (tmp_path / "pawn_sink_s1" / "hide.log").read_text()  # from its checkpoint
    # What came after the step that ran again was made again from it; the other case was left alone.
    audit = tmp_path / "pawn_sink_s1" / "audit.json"
    assert audit.stat().st_mtime_ns > (tmp_path / "pawn_sink_s1" / "hide" / "metrics.json").stat().st_mtime_ns
    assert (tmp_path / "mug_stand_s0" / "audit.json").stat().st_mtime_ns == mug_audit
    if PLOTS:  # a picture is drawn again only where a run it shows was
        assert pictures["mug_stand_s0"].stat().st_mtime_ns == drawn["mug_stand_s0"]
        assert pictures["pawn_sink_s1"].stat().st_mtime_ns > drawn["pawn_sink_s1"]

    # A study cut short, tabled as it stands: nothing runs, a sweep that had not ended is marked, a
    # container not yet swept is listed, and the AUCs keep the cases with every variant's row.
    (tmp_path / "pawn_sink_s1" / "robustness.done").unlink()
    (tmp_path / "mug_stand_s0" / "robustness_rdo" / "robustness.json").unlink()
    before = {f: f.stat().st_mtime_ns for f in tmp_path.rglob("metrics.json")}
    cut = study(tmp_path, "--report")
    assert cut.returncode == 0, cut.stderr + cut.stdout
    assert {f: f.stat().st_mtime_ns for f in tmp_path.rglob("metrics.json")} == before
    assert not (tmp_path / "pawn_sink_s1" / "robustness.done").is_file()
    result = json.loads((tmp_path / "study.json").read_text())
    assert [(r["case"], r["variant"], r["sweep_ended"]) for r in result["rows"]] == [
        ("mug_stand_s0", "default", True), ("pawn_sink_s1", "default", False), ("pawn_sink_s1", "rdo", True)]
    assert result["missing"] == ["mug_stand_s0 (rdo)"] and result["aucs"] == {}
    table = (tmp_path / "study.md").read_text()
    assert "| pawn_sink_s1 (sweep cut short) | default |" in table and "Not in the table" in table
    assert "No detection AUC" in table

    other = study(tmp_path, "--iterations", "30")
    assert other.returncode != 0 and "holds a run of other settings" in other.stderr


def test_bad_cases_are_refused_before_anything_trains(tmp_path):
    for case, message in (("teapot:stand:0", "the object must be one of"), ("mug:under:0", "placement must be one of"),
                          ("mug:stand:x", "the seed must be a non-negative integer"), ("mug:stand", "expected OBJECT"),
                          ("mug:stand:0:x", "the up axis must be one of"), ("nothing.obj:stand:0", "no mesh file"),
                          ("mug:stand:0:y", "an up axis turns a mesh file")):
        done = subprocess.run([sys.executable, str(SCRIPT), "--case", case, "--out", str(tmp_path)],
                              capture_output=True, text=True)
        assert done.returncode != 0 and message in done.stderr, (case, done.stderr)
    for variant, message in (("rdo --mode rdo", "expected NAME=FLAGS"), ("a b=--mode rdo", "expected NAME=FLAGS"),
                             ("default=--mode rdo", "names the defaults, without flags")):
        done = subprocess.run([sys.executable, str(SCRIPT), "--case", "mug:stand:0", "--variant", variant,
                               "--out", str(tmp_path)], capture_output=True, text=True)
        assert done.returncode != 0 and message in done.stderr, (variant, done.stderr)
    done = subprocess.run([sys.executable, str(SCRIPT), "--case", "mug:stand:0", "--devices", "cpu,gpu1",
                           "--out", str(tmp_path)], capture_output=True, text=True)
    assert done.returncode != 0 and "'gpu1' is not cpu, cuda or cuda:N" in done.stderr
    assert not any(tmp_path.iterdir())
