"""``backward_walk``: where the backward's back-to-front walk of each batch starts (the block's last
Gaussian or each warp's). Only the skipped work differs, so the gradients must not.
(The cooperative multi-thread path is checked in test_rasterizer_blocks.py.)"""
import pytest
import torch

from securegs_warp.raster_cases import assert_matches_reference, layered_scene, random_scene, render_with_grads
from securegs_warp.rasterizer import RasterOptions


@pytest.mark.parametrize("seed", [0, 3])
def test_warp_walk_matches_reference(seed):
    assert_matches_reference(random_scene(seed, n=80, backward_walk="warp"))


def test_warp_walk_gradients_equal_block_walk():
    # On the CPU a thread is its own block and its own warp, so both walks start at the pixel's own
    # last Gaussian (warp_max's CPU path must return it) and add in the same order: bit-identical.
    # Layered Gaussians make pixels stop at different depths.
    scene = layered_scene()
    block = render_with_grads(scene, backward_walk="block")
    warp = render_with_grads(scene, backward_walk="warp")
    assert len(block) == len(warp)
    for a, b in zip(block, warp):
        assert torch.equal(a, b)


def test_unknown_walk_is_refused():
    with pytest.raises(ValueError, match="backward_walk"):
        RasterOptions(backward_walk="tile")
