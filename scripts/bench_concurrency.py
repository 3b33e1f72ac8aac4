"""What a second CPU run costs: one `securegs train` alone against two at once, with torch's thread
count as the CLI sets it (half the cores) and as torch sets it by default (every core), side by side.

    python scripts/bench_concurrency.py                    # 128x96 built-in scene, 60 iterations

Prints the wall time of each configuration and the slowdown of two concurrent runs over one.
"""
import argparse
import statistics
import subprocess
import sys
import tempfile
import time

import torch

CHILD = ("import sys, securegs_warp.cli.common as common; common.cpu_threads = lambda: {threads}; "
         "from securegs_warp.cli import main; sys.exit(main(sys.argv[1:]))")


def wall_time(threads: int, runs: int, args: list[str]) -> float:
    """Seconds until ``runs`` concurrent `securegs train` processes with ``threads`` torch threads end."""
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        procs = [subprocess.Popen([sys.executable, "-c", CHILD.format(threads=threads), "train", "--out",
                                   f"{out}/run{i}", "--quiet", "--device", "cpu", *args],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for i in range(runs)]
        for p in procs:
            if p.wait() != 0:
                raise RuntimeError(p.stderr.read().decode())
        return time.perf_counter() - t0


def main():
    from securegs_warp.cli.common import cpu_threads

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=2, help="median over this many measurements")
    args = ap.parse_args()
    train = ["--iterations", str(args.iterations)]
    wall_time(1, 1, ["--iterations", "2"])  # compiles the kernels once
    settings = {f"CLI rule ({cpu_threads()} thread(s))": cpu_threads(),
                f"torch default ({torch.get_num_threads()} threads)": torch.get_num_threads()}
    print("| torch threads | one run s | two at once s | slowdown |\n|---|---|---|---|")
    for label, threads in settings.items():
        one = statistics.median(wall_time(threads, 1, train) for _ in range(args.repeats))
        two = statistics.median(wall_time(threads, 2, train) for _ in range(args.repeats))
        print(f"| {label} | {one:.1f} | {two:.1f} | {two / one:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
