"""evaluation.silhouette_regions and error_by_region: where a render's error lies against an
object's coverage."""
import math

import pytest
import torch

from securegs_warp.evaluation import REGIONS, error_by_region, silhouette_regions


def square_alpha(size=20, lo=5, hi=15):
    alpha = torch.zeros(size, size)
    alpha[lo:hi, lo:hi] = 1.0
    return alpha


def test_the_regions_split_every_pixel_once_around_the_boundary():
    regions = silhouette_regions(square_alpha(), band=2)
    total = sum(m.int() for m in regions.values())
    assert bool((total == 1).all())
    # A 10 px square, a band of 2 px each side of its edge: interior 6², band 14² − 6², outside the rest.
    assert int(regions["interior"].sum()) == 36
    assert int(regions["silhouette"].sum()) == 14 * 14 - 36
    assert int(regions["outside"].sum()) == 400 - 196
    assert bool(regions["silhouette"][5, 5]) and bool(regions["interior"][10, 10]) and bool(regions["outside"][0, 0])
    with pytest.raises(ValueError, match="band must be >= 1"):
        silhouette_regions(square_alpha(), band=0)


def test_error_by_region_puts_an_edge_error_on_the_silhouette():
    alpha = square_alpha()
    truth = alpha[..., None].expand(-1, -1, 3).clone()
    render = truth.clone()
    render[5, 5:15] = 0.5  # the square's top edge blurred
    render[10, 10] = 0.9   # one interior pixel off
    regions = error_by_region([(render, truth, alpha)], band=2)
    edge, inner = 10 * 3 * 0.25, 3 * 0.01
    assert regions["silhouette"]["error_share"] == pytest.approx(edge / (edge + inner))
    assert regions["interior"]["error_share"] == pytest.approx(inner / (edge + inner))
    assert regions["outside"]["error_share"] == 0.0 and math.isinf(regions["outside"]["psnr"])
    assert regions["interior"]["psnr"] == pytest.approx(10 * math.log10(3 * 36 / inner))
    assert sum(regions[r]["pixel_share"] for r in REGIONS) == pytest.approx(1.0)
    pooled = regions["all"]  # every pixel: the squared error over all of them
    assert pooled["error_share"] == pooled["pixel_share"] == 1.0
    assert pooled["psnr"] == pytest.approx(10 * math.log10(3 * 400 / (edge + inner)))
    with pytest.raises(ValueError, match="at least one"):
        error_by_region([])
