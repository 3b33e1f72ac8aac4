"""The accuracy-for-time options of ``rasterize``: ``fast_math`` and ``color_storage="float16"``.

Each variant is checked against the float64 reference with a tolerance that states its expected
error, and with its effect neutral against the general kernels.
"""
import pytest
import torch

from securegs_warp.raster_cases import (
    DIFF_INPUTS, GRAD_TOL, IMAGE_TOL, assert_matches_reference, float16_rounding, random_scene, relative_error,
    render_both, render_with_grads, run_with_cpu_blocks,
)
from securegs_warp.kernels.blend import batch_size, blend_kernels
from securegs_warp.kernels.projection import projection_kernel


def reference_errors(scene):
    """Max |Δ| of image and alpha, and the relative gradient error of each input, against the reference."""
    ours, ref = render_both(scene)
    errors = {key: float((ours[key] - ref[key]).abs().max()) for key in ("image", "alpha")}
    errors.update({name: relative_error(ours["grad_" + name], ref["grad_" + name]) for name in DIFF_INPUTS})
    return errors


# ---------------------------------------------------------------------------------------------
# color_storage="float16"

# Colour and background gradients do not read the colours (d image/d c_i = w_i, d image/d bg = T):
# they keep the float32 tolerance. The other gradients read each colour once, through
# d alpha_i = Σ_c (c_i T_i − buf_c/(1 − α_i))·v_c, so they inherit its relative rounding of at most
# 2⁻¹¹ ≈ 4.9e-4 (measured 0.3e-4 to 3.1e-4 on these scenes); 3e-3 leaves room for cancellation
# between the two terms.
FLOAT16_GRAD_TOL = 3e-3


@pytest.mark.parametrize("seed,channels,lo,hi", [(0, 3, 0.0, 1.0), (1, 16, -4.0, 4.0)])
def test_float16_colors_match_reference(seed, channels, lo, hi):
    scene = random_scene(seed, n=80, channels=channels, color_storage="float16")
    scene.colors = lo + (hi - lo) * scene.colors  # RGB, or signed feature values
    errors = reference_errors(scene)
    # The image is Σ wᵢcᵢ + T·bg with Σ wᵢ ≤ 1: its error is at most the largest colour rounding
    # (2.4e-4 for colours in [0, 1], 9.8e-4 for ±4; measured 1.6e-4 and 8.6e-4) plus the float32 error.
    assert errors["image"] <= float16_rounding(scene.colors) + IMAGE_TOL, errors
    assert errors["alpha"] <= IMAGE_TOL, errors
    for name in DIFF_INPUTS:
        tol = GRAD_TOL if name in ("colors", "background") else FLOAT16_GRAD_TOL
        assert errors[name] <= tol, (name, errors)


def test_float16_exactly_representable_colors_are_bit_identical():
    scene = random_scene(2, n=80, channels=5)
    scene.colors = torch.round(scene.colors * 256) / 256  # 8-bit colours: exact in float16
    general = render_with_grads(scene)
    half = render_with_grads(scene, color_storage="float16")
    for name, a, b in zip(["image", "alpha", *DIFF_INPUTS], general, half):
        assert torch.equal(a, b), name


def test_float16_overflow_raises():
    scene = random_scene(3, n=10)
    scene.colors[4, 1] = 1e5  # finite in float32, inf in float16
    with pytest.raises(ValueError, match="float16"):
        render_with_grads(scene, color_storage="float16")
    with pytest.raises(ValueError, match="color_storage"):
        render_with_grads(scene, color_storage="bfloat16")


def test_float16_batches_twice_the_wide_gaussians():
    # 64 channels: 288 B per float32 Gaussian overflow the shared-memory budget at 128 per batch.
    assert batch_size(64, 256, False, "float16", False) == 2 * batch_size(64, 256, False, "float32", False)


# The cooperative (CUDA) code path gathers the float16 colours into shared memory; run it on the
# CPU with real multi-thread blocks in a fresh process (enable_cpu_blocks is global).
COOPERATIVE = """
    from securegs_warp.raster_cases import error_row, float16_rounding, random_scene, render_both, render_with_grads

    scene = random_scene(4, n=70, channels=3, width=37, height=29, color_storage="float16", gather=GATHER)
    ours, ref = render_both(scene)
    row = {**error_row(ours, ref), "bound": float16_rounding(scene.colors)}
    scene.colors = torch.round(scene.colors * 256) / 256
    general = render_with_grads(scene, gather=GATHER)
    half = render_with_grads(scene, color_storage="float16", gather=GATHER)
    row["identical"] = all(torch.equal(a, b) for a, b in zip(general, half))
    print("RESULT" + json.dumps(row))
"""


@pytest.mark.parametrize("gather", ["fields", "packed"])  # packed: colours in their own float16 batch
def test_float16_cooperative_blocks(gather):
    row = run_with_cpu_blocks(COOPERATIVE.replace("GATHER", repr(gather)))
    assert row["identical"], row
    assert row["image"] <= row["bound"] + IMAGE_TOL, row
    for name in DIFF_INPUTS:
        assert row[name] <= (GRAD_TOL if name in ("colors", "background") else FLOAT16_GRAD_TOL), (name, row)


# ---------------------------------------------------------------------------------------------
# fast_math

# Same tolerances as the exact kernels. On the CPU Warp 1.19 does not pass fast_math to its
# compiler (measured: bit-identical results). On CUDA it is nvcc --use_fast_math: __expf is within
# 2 + ⌊1.17·|x|⌋ ulp, and only e^{-σ} with σ ≤ ln 255 is used (a larger σ gives α < 1/255, skipped),
# so ≤ 8 ulp ≈ 5e-7 relative; division and square root are within 2 ulp, and denormals
# flushed to zero lie far below 1e-4. Errors stay ~1e-6, as for the exact kernels.
@pytest.mark.parametrize("seed", [0, 1])
def test_fast_math_matches_reference(seed):
    assert_matches_reference(random_scene(seed, n=80, fast_math=True))


def test_fast_math_with_float16_colors():
    scene = random_scene(5, n=60, fast_math=True, color_storage="float16")
    errors = reference_errors(scene)
    assert errors["image"] <= float16_rounding(scene.colors) + IMAGE_TOL, errors
    assert max(errors[name] for name in DIFF_INPUTS) <= FLOAT16_GRAD_TOL, errors


def test_fast_math_is_a_module_option_of_its_own_kernels():
    slow, fast = (projection_kernel(False, "opacity_aware", f) for f in (False, True))
    assert slow.module is not fast.module
    assert slow.module.options["fast_math"] is False and fast.module.options["fast_math"] is True
    for kernel in blend_kernels(3, 16, False, 32, False, "float32", True, packed=False):
        assert kernel.module.options["fast_math"] is True


def test_fast_math_off_is_the_default():
    scene = random_scene(6, n=60)
    for a, b in zip(render_with_grads(scene), render_with_grads(scene, fast_math=False)):
        assert torch.equal(a, b)
