"""The cooperative (CUDA) code path of the blending kernels, exercised on the CPU.

On the CPU Warp normally runs one thread per block, so the shared-memory batches, block votes and
block reductions are trivial there. With ``wp.config.enable_cpu_blocks`` it runs real blocks of
many threads; this test renders with several block shapes in a fresh process (the flag is global)
and checks every result against the float64 reference.
"""
import pytest

from securegs_warp.raster_cases import DIFF_INPUTS, run_with_cpu_blocks

SCRIPT = """
    from securegs_warp.raster_cases import error_row, layered_scene, random_scene, render_both

    out = []
    # (forward block, backward block, backward walk, backward pixels a thread)
    for blocks in [(256, 32, "block", 1), (64, 64, "block", 1), (32, 256, "block", 1), (64, 64, "warp", 1),
                   (256, 256, "block", 2), (64, 32, "warp", 2)]:
        for name, scene in [("random", random_scene(30, n=70, width=37, height=29)), ("layers", layered_scene())]:
            scene.kwargs.update(forward_block=blocks[0], backward_block=blocks[1], backward_walk=blocks[2],
                                backward_pixels=blocks[3], gather=GATHER)
            ours, ref = render_both(scene)
            out.append({"blocks": blocks, "scene": name, **error_row(ours, ref)})
    print("RESULT" + json.dumps(out))
"""


@pytest.mark.parametrize("gather", ["fields", "packed"])
def test_multithreaded_blocks_match_reference(gather):
    rows = run_with_cpu_blocks(SCRIPT.replace("GATHER", repr(gather)))
    assert len(rows) == 12
    for row in rows:
        assert row["image"] <= 1e-4 and row["alpha"] <= 1e-4, row
        for name in DIFF_INPUTS:
            assert row[name] <= 1e-3, (name, row)
