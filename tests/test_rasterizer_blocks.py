"""The cooperative (CUDA) code path of the blending kernels, exercised on the CPU.

On the CPU Warp normally runs one thread per block, so the shared-memory batches, block votes and
block reductions are trivial there. With ``wp.config.enable_cpu_blocks`` it runs real blocks of
many threads; this test renders with several block shapes in a fresh process (the flag is global)
and checks every result against the float64 reference.
"""
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

SCRIPT = textwrap.dedent("""
    import json, sys
    import torch
    import warp as wp
    wp.config.quiet = True
    wp.config.enable_cpu_blocks = True
    sys.path.insert(0, sys.argv[1])
    from raster_cases import random_scene, render_both, relative_error, DIFF_INPUTS
    from test_rasterizer import _scene, _aniso

    def layers():
        z = torch.cat([torch.linspace(2.0, 3.0, 300), torch.linspace(3.01, 4.0, 40)])
        means = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], dim=1)
        means[:, :2] += torch.randn(340, 2, generator=torch.Generator().manual_seed(3)) * 0.05
        opac = torch.cat([torch.full((300,), 0.015), torch.full((40,), 0.6)])
        return _scene(means, opacities=opac, scales=_aniso(340, 0.05), width=20, height=18)

    out = []
    for blocks in [(256, 32), (64, 64), (32, 256)]:
        for name, scene in [("random", random_scene(30, n=70, width=37, height=29)), ("layers", layers())]:
            scene.kwargs.update(forward_block=blocks[0], backward_block=blocks[1])
            ours, ref = render_both(scene)
            row = {"blocks": blocks, "scene": name,
                   "image": float((ours["image"] - ref["image"]).abs().max()),
                   "alpha": float((ours["alpha"] - ref["alpha"]).abs().max())}
            row.update({n: relative_error(ours["grad_" + n], ref["grad_" + n]) for n in DIFF_INPUTS})
            out.append(row)
    print("RESULT" + json.dumps(out))
""")


def test_multithreaded_blocks_match_reference():
    tests_dir = str(Path(__file__).parent)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, tests_dir], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(proc.stdout.split("RESULT", 1)[1])
    assert len(rows) == 6
    for row in rows:
        assert row["image"] <= 1e-4 and row["alpha"] <= 1e-4, row
        for name in ("means", "quats", "scales", "opacities", "colors", "background"):
            assert row[name] <= 1e-3, (name, row)
