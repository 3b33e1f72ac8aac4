"""A study of hiding cases: per case a plain model and a container of one seed, the audit, the attacks;
then one table and the audit's detection AUC over all cases. Cases run side by side over the given
devices (each in its own processes), and a rerun picks up where an interrupted one stopped.

A case is ``OBJECT:PLACEMENT:SEED[:UP]``: a built-in object name or a mesh file, ``stand`` (mostly in
empty space), ``sink`` (half inside a host object) or ``float``, the training seed, and a mesh file's
up axis (z unless given). Give each case its own seed: the plain models are then distinct covers,
and each container is audited against the plain models of the other cases only.

Per case, in OUT/NAME (NAME = object_placement_sSEED), and per variant (``--variant V="FLAGS"``: extra
``securegs hide`` flags; none given: the default alone, whose files carry no _V), where FLAGS are
``--width W --height H --iterations N --quiet [--scene SCENE]``:
    securegs train FLAGS --seed SEED --out OUT/NAME/plain
    securegs hide FLAGS --seed SEED --hide OBJECT --placement PLACEMENT [--hidden-up UP] [V's FLAGS] \\
        --out OUT/NAME/hide_V
    securegs audit OUT/NAME/hide_V/public --reference OUT/NAME/plain/model --key OUT/NAME/hide_V/key.safetensors --json
    python scripts/robustness.py OUT/NAME/hide_V --attacks ATTACKS --draws DRAWS --out OUT/NAME/robustness_V \\
        [--without-record]
Then OUT/study.md and OUT/study.json: one row per case and variant, and each variant's detection AUC
(``steganalysis.auc_by_model``, as ``scripts/audit_auc.py`` computes it) over all cases and per placement;
and per case OUT/NAME/anchor_clouds.png: the anchors near the hidden object, from above and from the side,
of the plain model and each variant, beside the hidden surface that the first variant's key decodes (the
audit's measure of the leak); it needs matplotlib (``pip install -e ".[plots]"``).
``--report`` (the same arguments) runs nothing and tables what the folders hold, for a study cut
short (a lease that ended): its rows mark a sweep that had not ended, and its AUCs take the cases
that have every variant's row.

    python scripts/hiding_study.py --case mug:stand:0 --case mug:sink:1 --out runs/study      # the CPU
    python scripts/hiding_study.py --case mug:stand:0 --case mug:stand:1 --variant rdo="--mode rdo"   # and the paper's
    python scripts/hiding_study.py --scene garden --case mug:stand:2 --case bunny.obj:sink:3:y --out runs/garden
    python scripts/hiding_study.py --width 1920 --height 1080 --iterations 4000 --devices cuda:0,cuda:1 \\
        --per-device 2 --case mug:stand:5 --case ogre.obj:stand:8:y --case mug:sink:13 --out runs/study1080
"""
import argparse
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import threading
from pathlib import Path

import torch

from securegs_warp.compare import BASELINE, read_run_anchors
from securegs_warp.data.meshes import HIDDEN_OBJECTS, MESH_SUFFIXES, UP_AXES
from securegs_warp.data.synthetic import PLACEMENTS, SCENES
from securegs_warp.io.atomic import atomic_write
from securegs_warp.robustness import SWEEP
from securegs_warp.keys import KeyFileError
from securegs_warp.secure.container import open_container
from securegs_warp.secure.security import plot_anchor_clouds
from securegs_warp.secure.steganalysis import NoHiddenSurface, auc_by_model, key_surface

# The variant without extra flags; its folders and files carry no suffix.
DEFAULT = "default"
SCRIPTS = Path(__file__).resolve().parent
# What a row reports of each attack in the sweep (the others stay in the case's robustness.md).
REPORTED = ("prune-random:0.2", "prune-random:0.3", "noise-feat:0.1", "purify:0.2", "quantize:12", "quantize:10",
            "quantize:8", "quantize:6", "noise-xyz:0.005", "noise-xyz:0.01")


def parse_case(text: str) -> dict:
    """``OBJECT:PLACEMENT:SEED[:UP]`` -> {object, placement, seed, up, name}; SystemExit naming what is wrong."""
    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise SystemExit(f"--case {text!r}: expected OBJECT:PLACEMENT:SEED[:UP]")
    obj, placement, seed, up = (parts + ["z"])[:4]
    if placement not in PLACEMENTS:
        raise SystemExit(f"--case {text!r}: placement must be one of {', '.join(PLACEMENTS)}, got {placement!r}")
    if not seed.isdigit():
        raise SystemExit(f"--case {text!r}: the seed must be a non-negative integer, got {seed!r}")
    if up not in UP_AXES:
        raise SystemExit(f"--case {text!r}: the up axis must be one of {', '.join(UP_AXES)}, got {up!r}")
    # Checked here rather than when the hide step fails, after the plain model has trained.
    if Path(obj).suffix.lower() in MESH_SUFFIXES:
        if not Path(obj).is_file():
            raise SystemExit(f"--case {text!r}: no mesh file {obj}")
        obj = str(Path(obj).resolve())
    elif obj not in HIDDEN_OBJECTS:
        raise SystemExit(f"--case {text!r}: the object must be one of {sorted(HIDDEN_OBJECTS)} or a mesh file "
                         f"({', '.join(MESH_SUFFIXES)}), got {obj!r}")
    elif up != "z":
        raise SystemExit(f"--case {text!r}: an up axis turns a mesh file; the built-in {obj!r} stands as it is")
    return {"object": obj, "placement": placement, "seed": int(seed), "up": up,
            "name": f"{Path(obj).stem}_{placement}_s{seed}"}


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``NAME=FLAGS`` -> (NAME, the flags, split as a shell would); SystemExit naming what is wrong."""
    name, sep, flags = text.partition("=")
    if not sep or not re.fullmatch(r"[A-Za-z0-9-]+", name):
        raise SystemExit(f"--variant {text!r}: expected NAME=FLAGS, NAME of letters, digits and '-'")
    if name == DEFAULT and flags.strip():
        raise SystemExit(f"--variant {text!r}: {DEFAULT!r} names the defaults, without flags; name the variant")
    return name, shlex.split(flags)


def suffix(variant: str) -> str:
    """What a variant's folders and files end with: nothing for DEFAULT."""
    return "" if variant == DEFAULT else f"_{variant}"


def sweep_flags(sweep: dict) -> list[str]:
    """scripts/robustness.py's flags for ``sweep``: {"attacks", "draws"[, "without_record": True]}."""
    return ["--attacks", sweep["attacks"], "--draws", str(sweep["draws"]),
            *(["--without-record"] if sweep.get("without_record") else [])]


def steps(case: dict, run: Path, flags: list[str], variants: dict, sweep: dict,
          device: str) -> list[tuple[str, Path, list[str]]]:
    """The case's commands in order: (name, the file whose presence says it is done, command)."""
    cli = [sys.executable, "-m", "securegs_warp.cli"]
    on = ["--device", device, "--seed", str(case["seed"])]
    hidden = ["--hide", case["object"], "--placement", case["placement"], "--hidden-up", case["up"]]
    plain = run / "plain"

    def again(folder):  # an interrupted training resumes; a folder without a checkpoint starts over
        return ["--resume"] if (folder / "checkpoint.pt").is_file() else ["--force"]

    out = [("plain", plain / "metrics.json", cli + ["train", *flags, *on, "--out", str(plain), *again(plain)])]
    for variant, extra in variants.items():
        end = suffix(variant)
        hide, robustness = run / f"hide{end}", run / f"robustness{end}"
        out += [
            (f"hide{end}", hide / "metrics.json",
             cli + ["hide", *flags, *on, *hidden, *extra, "--out", str(hide), *again(hide)]),
            (f"audit{end}", run / f"audit{end}.json",
             cli + ["audit", str(hide / "public"), "--reference", str(plain / "model"), "--key",
                    str(hide / "key.safetensors"), "--json"]),
            # robustness.json is rewritten after every attack: a marker says the sweep ended.
            (f"robustness{end}", run / f"robustness{end}.done",
             [sys.executable, str(SCRIPTS / "robustness.py"), str(hide), *sweep_flags(sweep),
              "--device", device, "--out", str(robustness)]),
        ]
    return out


def settings(case: dict, flags: list[str], variants: dict, sweep: dict, devices: list[str]) -> str:
    """What a case's results depend on, as the text of its case.json: a rerun with other settings
    must not reuse them. The kind of device counts (the tile size follows it, and so the cover)."""
    kinds = sorted({d.split(":")[0] for d in devices})
    return json.dumps({"case": case, "flags": flags, "variants": variants, **sweep, "devices": kinds},
                      sort_keys=True)


def run_case(case: dict, out: Path, flags: list[str], variants: dict, sweep: dict, device: str) -> str | None:
    """Every step of one case not done yet, on ``device``; None, or what failed and where its log is.
    Once a step runs, every step after it runs again: its results may rest on the old ones."""
    run = out / case["name"]
    env = dict(os.environ)
    if device.startswith("cuda:"):  # one GPU a process, which sees only its own
        env["CUDA_VISIBLE_DEVICES"] = device.split(":", 1)[1]
        device = "cuda"
    stale = False
    for name, done, command in steps(case, run, flags, variants, sweep, device):
        if done.is_file() and not stale:
            continue
        stale = True
        done.unlink(missing_ok=True)
        log = run / f"{name}.log"
        with open(log, "w") as f:
            if name.startswith("audit"):  # its one JSON object is the result: written whole or not at all
                result = subprocess.run(command, stdout=subprocess.PIPE, stderr=f, env=env)
                if result.returncode == 0:
                    atomic_write(done, lambda g: g.write(result.stdout))
            else:
                result = subprocess.run(command, stdout=f, stderr=subprocess.STDOUT, env=env)
                if result.returncode == 0 and done.suffix == ".done":
                    atomic_write(done, lambda g: None)
        if result.returncode != 0:
            return f"{case['name']}: {name} failed (exit {result.returncode}); see {log}"
    return None


def case_rows(case: dict, run: Path, variants) -> list[dict]:
    """The table's rows of one case, one per variant whose container has been trained, audited and
    swept, in part at least: ``sweep_ended`` says whether its sweep ran to the end (a finished case
    has every row, each sweep ended; ``--report`` tables what a cut-short study left)."""
    if not (run / "plain" / "metrics.json").is_file():
        return []
    plain = json.loads((run / "plain" / "metrics.json").read_text())
    rows = []
    for variant in variants:
        end = suffix(variant)
        files = (run / f"hide{end}" / "metrics.json", run / f"audit{end}.json",
                 run / f"robustness{end}" / "robustness.json")
        if not all(f.is_file() for f in files):
            continue
        hide, audit, swept = (json.loads(f.read_text()) for f in files)
        # The container's own rows: a sweep --without-record also holds the key's without the record.
        sweep = {s["spec"]: s for s in swept["summary"] if s["model"] == f"hide{end}"}
        rows.append({
            "case": case["name"], "variant": variant, "sweep_ended": (run / f"robustness{end}.done").is_file(),
            "cover_plain": plain["psnr"], "cover": hide["psnr_public"],
            "cover_change": hide["psnr_public"] - plain["psnr"], "hidden": hide.get("psnr_hidden"),
            "hidden_ssim": hide.get("ssim_hidden"), "bits": hide.get("bit_accuracy"),
            "size_ratio": hide["size_mb_public"] / plain["size_mb"], "density_ratio": audit.get("density_ratio"),
            "coverage": audit.get("coverage"), "coverage_plain": audit.get("reference_coverage"),
            "audit_score": audit["score"],
            "attacks": {spec: {k: sweep[spec][k] for k in ("delta_mean", "delta_worst", "bit_accuracy_worst")}
                        for spec in REPORTED if spec in sweep}})
    return rows


def markdown(rows: list[dict], aucs: dict) -> str:
    """The cases' table (``case_rows``' rows), then the AUCs' (``study_aucs``)."""
    fmt = lambda v, f="{:.2f}": "–" if v is None else f.format(v)  # noqa: E731
    specs = [s for s in REPORTED if any(s in r["attacks"] for r in rows)]
    head = ["case", "variant", "plain cover dB", "cover dB (Δ)", "hidden dB / SSIM", "bits", "release ÷ plain",
            "density ratio", "coverage (plain)", "audit score"] + [f"{s}: mean / worst dB, bits" for s in specs]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        cells = [r["case"] + ("" if r["sweep_ended"] else " (sweep cut short)"), r["variant"], fmt(r["cover_plain"]),
                 f"{fmt(r['cover'])} ({fmt(r['cover_change'], '{:+.2f}')})",
                 f"{fmt(r['hidden'])} / {fmt(r['hidden_ssim'], '{:.4f}')}", fmt(r["bits"], "{:.0%}"),
                 fmt(r["size_ratio"]), fmt(r["density_ratio"]),
                 f"{fmt(r['coverage'], '{:.3f}')} ({fmt(r['coverage_plain'], '{:.3f}')})",
                 fmt(r["audit_score"], "{:.1f}")]
        for s in specs:
            a = r["attacks"].get(s)
            cells.append("–" if a is None else
                         f"{fmt(a['delta_mean'], '{:+.2f}')} / {fmt(a['delta_worst'], '{:+.2f}')}, "
                         f"{fmt(a['bit_accuracy_worst'], '{:.0%}')}")
        lines.append("| " + " | ".join(cells) + " |")
    if not aucs:
        return "\n".join(lines + ["", "No detection AUC: it needs two cases or more with every variant's row."]) + "\n"
    lines += ["", "| detection AUC of the audit (0.5: chance) | variant | without a reference | with a reference |",
              "|---|---|---|---|"]
    for subset, by_variant in aucs.items():
        for variant, pair in by_variant.items():
            cells = [subset, variant, fmt(pair.get("without")), fmt(pair.get("with"))]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def study_aucs(cases: list[dict], out: Path, variants) -> dict:
    """{subset: {variant: {"without", "with"}}}: each variant's AUC over every case and over each
    placement with two or more cases; "with" is left out where the cases share one cover."""
    aucs = {}
    for subset in ("all", *PLACEMENTS):
        chosen = [c for c in cases if subset == "all" or c["placement"] == subset]
        if len(chosen) < 2:
            continue
        runs, covers = [], []
        for c in chosen:
            cover, _, plain = read_run_anchors(out / c["name"] / "plain")
            runs.append({BASELINE: plain, **{v: read_run_anchors(out / c["name"] / f"hide{suffix(v)}")[2]
                                            for v in variants}})
            covers.append(cover)
        pairs = {v: {} for v in variants}
        for key, with_reference in (("without", False), ("with", True)):
            try:
                result = auc_by_model(runs, BASELINE, with_reference, covers)
            except ValueError:  # every case of one cover: no reference trained apart
                continue
            for v in variants:
                pairs[v][key] = result[v]["auc"]
        aucs[subset] = pairs
    return aucs


def draw_clouds(case: dict, out: Path, variants) -> str:
    """OUT/NAME/anchor_clouds.png of a case whose plain model and containers are trained and audited:
    the plain model's anchors and each variant's around the surface the first variant's key decodes.
    Returns what was done, or why no picture was drawn (not trained yet, a key that cannot be opened
    or marks no surface). A picture newer than every run it shows is kept (drawing it renders the
    key's hidden views again)."""
    run = out / case["name"]
    path = run / "anchor_clouds.png"
    folders = {"plain Scaffold-GS": run / "plain", **{v: run / f"hide{suffix(v)}" for v in variants}}
    inputs = [f / "metrics.json" for f in folders.values()] + [run / f"audit{suffix(v)}.json" for v in variants]
    if not all(f.is_file() for f in inputs):
        return f"{case['name']}: no anchor-cloud picture (not trained and audited yet)"
    if path.is_file() and path.stat().st_mtime_ns >= max(f.stat().st_mtime_ns for f in inputs):
        return f"kept {path}"
    first = run / f"hide{suffix(next(iter(variants)))}"
    try:
        model, meta = open_container(first / "public", first / "key.safetensors", device="cpu")
        with torch.no_grad():
            surface, _ = key_surface(model, meta)
    except (KeyFileError, NoHiddenSurface) as why:
        return f"{case['name']}: no anchor-cloud picture ({why})"
    clouds = {name: read_run_anchors(folder)[2] for name, folder in folders.items()}
    plot_anchor_clouds(path, clouds, surface)
    return f"wrote {path}"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", action="append", required=True, help="OBJECT:PLACEMENT:SEED[:UP], repeatable")
    ap.add_argument("--scene", choices=sorted(SCENES), default=None,
                    help="the built-in cover scene of every case (default: securegs's own, the room)")
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--iterations", type=int, default=400)
    ap.add_argument("--variant", action="append", default=[],
                    help='NAME="FLAGS": extra securegs hide flags of a container kind, repeatable (default: the '
                         f'defaults alone, named {DEFAULT!r}); e.g. rdo="--mode rdo"')
    ap.add_argument("--attacks", default="prune-random,noise-feat",
                    help=f"attacks of the sweep (scripts/robustness.py; known: {','.join(SWEEP)})")
    ap.add_argument("--draws", type=int, default=3, help="draws of each random attack")
    ap.add_argument("--without-record", action="store_true",
                    help="sweep each container's key without its record of the serving anchors as well "
                         "(scripts/robustness.py --without-record; in the case's robustness.md)")
    ap.add_argument("--devices", default="cpu", help="comma-separated: cpu, cuda, cuda:N (default: cpu)")
    ap.add_argument("--per-device", type=int, default=1, help="cases at once on each device")
    ap.add_argument("--out", default="runs/study")
    ap.add_argument("--report", action="store_true",
                    help="run nothing: table what the cases' folders hold now (a study cut short: the rows of "
                         "the containers trained, audited and swept, a sweep that had not ended marked; the "
                         "AUCs over the cases with every variant's row)")
    args = ap.parse_args()
    cases = [parse_case(c) for c in args.case]
    variants = dict(parse_variant(v) for v in args.variant) or {DEFAULT: []}
    if len(variants) != len(args.variant or [DEFAULT]):
        raise SystemExit("two variants share a name")
    names = [c["name"] for c in cases]
    if len(set(names)) != len(names):
        raise SystemExit(f"two cases share a name: {sorted(n for n in names if names.count(n) > 1)}")
    unknown = sorted(set(args.attacks.split(",")) - set(SWEEP))
    if unknown:
        raise SystemExit(f"unknown attacks {unknown}; known: {', '.join(SWEEP)}")
    if args.per_device < 1 or args.draws < 1:
        raise SystemExit("--per-device and --draws must be at least 1")
    devices = args.devices.split(",")
    bad = [d for d in devices if not re.fullmatch(r"cpu|cuda(:\d+)?", d)]
    if bad:
        raise SystemExit(f"--devices: {', '.join(map(repr, bad))} is not cpu, cuda or cuda:N")
    out = Path(args.out)
    flags = ["--width", str(args.width), "--height", str(args.height), "--iterations", str(args.iterations),
             "--quiet"] + (["--scene", args.scene] if args.scene else [])
    # Every case's settings checked before anything trains, then recorded.
    sweep = {"attacks": args.attacks, "draws": args.draws, **({"without_record": True} if args.without_record else {})}
    wanted = {c["name"]: settings(c, flags, variants, sweep, devices) for c in cases}
    for name, text in wanted.items():
        recorded = out / name / "case.json"
        if recorded.is_file() and recorded.read_text() != text:
            raise SystemExit(f"{out / name} holds a run of other settings ({recorded}); give another --out")
    if not args.report:
        run_cases(cases, out, wanted, flags, variants, sweep, devices, args.per_device)
    rows = {c["name"]: case_rows(c, out / c["name"], variants) for c in cases}
    missing = [f"{c['name']} ({v})" for c in cases for v in variants
               if v not in {r["variant"] for r in rows[c["name"]]}]
    whole = [c for c in cases if len(rows[c["name"]]) == len(variants)]
    aucs = study_aucs(whole, out, variants)
    table_rows = [r for c in cases for r in rows[c["name"]]]
    table = markdown(table_rows, aucs)
    if missing:
        table += f"\nNot in the table (not trained, audited and swept yet): {', '.join(missing)}.\n"
    out.mkdir(parents=True, exist_ok=True)  # --report on a folder a study never reached
    atomic_write(out / "study.md", lambda f: f.write(table.encode()))
    data = json.dumps({"args": vars(args), "rows": table_rows, "aucs": aucs, "missing": missing}, indent=1).encode()
    atomic_write(out / "study.json", lambda f: f.write(data))
    print(table)
    if importlib.util.find_spec("matplotlib") is None:
        print("no anchor-cloud pictures: matplotlib is not installed (pip install -e \".[plots]\")")
        return
    for c in cases:
        print(draw_clouds(c, out, variants))


def run_cases(cases: list[dict], out: Path, wanted: dict, flags: list[str], variants: dict, sweep: dict,
              devices: list[str], per_device: int) -> None:
    """Record each case's settings (``wanted``: name -> settings JSON), then run every case's steps not
    done yet, ``per_device`` cases at once on each device; SystemExit listing the failures."""
    for name, text in wanted.items():
        (out / name).mkdir(parents=True, exist_ok=True)
        atomic_write(out / name / "case.json", lambda f, text=text: f.write(text.encode()))
    queue, failures, lock = list(cases), [], threading.Lock()

    def worker(device):
        while True:
            with lock:
                if not queue:
                    return
                case = queue.pop(0)
            print(f"{case['name']} on {device}", flush=True)
            failure = run_case(case, out, flags, variants, sweep, device)
            with lock:
                if failure:
                    failures.append(failure)
                else:
                    print(f"{case['name']} done", flush=True)

    workers = [threading.Thread(target=worker, args=(d,)) for d in devices for _ in range(per_device)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    if failures:
        raise SystemExit("\n".join(failures))


if __name__ == "__main__":
    main()
