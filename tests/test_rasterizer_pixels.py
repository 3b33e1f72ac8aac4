"""``backward_pixels``: pixels each thread of the backward blending kernel walks. A thread reads each
Gaussian once for its pixels and sums their gradients before the warp's reduction; only that order
of float sums may differ, so the gradients must match the float64 reference and the one-pixel walk.
(The cooperative multi-thread path is checked in test_rasterizer_blocks.py.)"""
import pytest

from securegs_warp.raster_cases import (GRAD_TOL, assert_matches_reference, layered_scene, random_scene,
                                        relative_error, render_with_grads)
from securegs_warp.rasterizer import RasterOptions


@pytest.mark.parametrize("seed,tile_size,channels,pixels", [(0, 16, 3, 2), (3, 8, 3, 2), (5, 16, 16, 2),
                                                            (0, 16, 3, 4), (3, 32, 3, 4)])
def test_several_pixels_a_thread_match_reference(seed, tile_size, channels, pixels):
    # Odd image sizes leave tiles whose last pixel rows lie outside the image.
    assert_matches_reference(random_scene(seed, n=80, channels=channels, width=41, height=31,
                                          tile_size=tile_size, backward_pixels=pixels))


@pytest.mark.parametrize("pixels", [2, 4])
def test_several_pixels_a_thread_match_one_on_long_lists(pixels):
    # Layered Gaussians: the pixels stop at different depths and walk several batches.
    scene = layered_scene()
    one = render_with_grads(scene, backward_pixels=1)
    several = render_with_grads(scene, backward_pixels=pixels)
    assert len(one) == len(several)
    for a, b in zip(one, several):
        assert relative_error(b, a) <= GRAD_TOL


@pytest.mark.parametrize("pixels,tile_size", [(0, 16), (3, 16), (8, 16), (4, 8)])
def test_bad_pixel_counts_are_refused(pixels, tile_size):
    # Four pixels a thread would leave a tile of 8 with 16 threads, less than the warp its sums need.
    with pytest.raises(ValueError, match="backward_pixels"):
        RasterOptions(backward_pixels=pixels, tile_size=tile_size)
