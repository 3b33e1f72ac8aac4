"""securegs_warp.benchmark on the CPU: command-line options are parsed by their field's type and bad
ones refused with a message that says what is wrong, the benchmark scenes have the documented shapes,
``timed`` returns a positive time, and one small benchmark row and its table hold their columns."""
import math

import pytest
import torch

from securegs_warp import RasterOptions, UnknownOptionError, benchmark


def test_parse_options_types_each_field():
    options = benchmark.parse_options("tile_size=8, fast_math=true,alpha_min=0.01,radius_rule=3sigma,"
                                      "render_depth=expected,antialiased=False")
    assert options == RasterOptions(tile_size=8, fast_math=True, alpha_min=0.01, radius_rule="3sigma",
                                    render_depth="expected", antialiased=False)
    assert isinstance(options.alpha_min, float) and options.tile_size == 8
    assert benchmark.parse_options("") == RasterOptions()
    assert benchmark.parse_options("render_depth=none", RasterOptions(render_depth="expected")).render_depth is None
    assert benchmark.parse_options("fast_math=true", RasterOptions(tile_size=8)).tile_size == 8  # on the base
    assert benchmark.parse_options(benchmark.options_text(options)) == options


def test_parse_variant():
    assert benchmark.parse_variant("b64:backward_block=64") == ("b64", RasterOptions(backward_block=64))
    assert benchmark.parse_variant("plain") == ("plain", RasterOptions())


@pytest.mark.parametrize("text,message", [
    ("tile_sise=8", r"unknown rasterize option\(s\) 'tile_sise'; valid RasterOptions fields: .*tile_size"),
    ("tile_size", r"'tile_size' is not key=value"),
    ("=8", r"'=8' is not key=value"),
    ("tile_size=8,tile_size=16", "tile_size given twice"),
    ("tile_size=eight", r"option tile_size: expected an integer, got 'eight'"),
    ("alpha_min=1/255", r"option alpha_min: expected a number, got '1/255'"),
    ("fast_math=yes", r"option fast_math: expected true or false, got 'yes'"),
    ("tile_size=12", "tile_size must be 8, 16 or 32, got 12"),
    ("color_storage=bfloat16", "color_storage must be one of"),
])
def test_parse_options_refuses_bad_input(text, message):
    with pytest.raises(ValueError, match=message):
        benchmark.parse_options(text)


def test_parse_variant_refuses_bad_input():
    with pytest.raises(ValueError, match="has no name"):
        benchmark.parse_variant(":tile_size=8")
    with pytest.raises(UnknownOptionError, match="blocks"):
        benchmark.parse_variant("b:blocks=64")


@pytest.mark.parametrize("kind", benchmark.SCENE_KINDS)
def test_make_scene_shapes(kind):
    scene = benchmark.make_scene(kind, 50, "cpu")
    shapes = {name: tuple(t.shape) for name, t in scene.items()}
    assert shapes == {"means": (50, 3), "quats": (50, 4), "scales": (50, 3), "opacities": (50,), "colors": (50, 3)}
    assert all(t.dtype == torch.float32 for t in scene.values())
    assert ((scene["opacities"] >= 0) & (scene["opacities"] <= 1)).all() and (scene["scales"] > 0).all()
    assert torch.equal(scene["means"], benchmark.make_scene(kind, 50, "cpu")["means"])  # seeded


def test_make_scene_refuses_an_unknown_kind():
    with pytest.raises(ValueError, match="unknown scene kind 'uniform'; known: random, realistic"):
        benchmark.make_scene("uniform", 10, "cpu")


def test_camera_and_cotangents_shapes():
    viewmat, K = benchmark.camera(64, 36, "cpu")
    assert viewmat.shape == (4, 4) and K.shape == (3, 3)
    assert K[0, 0] == pytest.approx(1100 * 64 / 1920) and (K[0, 2], K[1, 2]) == (32, 18)
    image, alpha = benchmark.cotangents(64, 36, "cpu")
    assert image.shape == (36, 64, 3) and alpha.shape == (36, 64, 1)


def test_timed_returns_a_positive_median():
    scene = benchmark.make_scene("random", 200, "cpu")
    for t in scene.values():
        t.requires_grad_(True)
    viewmat, K = benchmark.camera(32, 24, "cpu")
    grads = benchmark.cotangents(32, 24, "cpu")
    options = RasterOptions.for_device("cpu")

    def fn():
        return benchmark.ours(scene, viewmat, K, 32, 24, options)

    for backward in (False, True):
        ms = benchmark.timed(fn, backward, "cpu", 1, 3, grads)
        assert isinstance(ms, float) and ms > 0 and math.isfinite(ms)
    assert scene["means"].grad is not None and torch.isfinite(scene["means"].grad).all()
    with pytest.raises(ValueError, match="runs >= 1"):
        benchmark.timed(fn, False, "cpu", 0, 0, grads)


def test_benchmark_scene_row_and_table():
    variants = [("t32", RasterOptions(tile_size=32))]
    row = benchmark.benchmark_scene("realistic", 300, 48, 32, "cpu", RasterOptions(tile_size=8), variants,
                                    warmup=0, runs=1)
    for name in ("ours", "t32"):
        assert row[f"{name}_fwd_ms"] > 0 and row[f"{name}_fwdbwd_ms"] > 0
    assert row["intersections"] > 0 and 0 < row["visible"] <= 300 and "breakdown_ms" not in row
    # Another tile size: the same gradients up to float32 summation order.
    assert 0.0 <= row["t32_max_grad_diff"] < 1e-4
    table = benchmark.benchmark_table([row], "title")
    assert "| Δgrad vs ours |" in table and f"| {row['t32_max_grad_diff']:.1e} |" in table
    assert table.startswith("title\n\n| scene | N |") and "| realistic | 300 |" in table
    with pytest.raises(ValueError, match="'ours' is taken"):
        benchmark.benchmark_scene("random", 10, 8, 8, "cpu", variants=[("ours", RasterOptions())])


def test_kernel_breakdown_gets_the_timed_options(monkeypatch):
    """The per-kernel breakdown (CUDA only, stubbed here: it calls the renderer once) renders each
    renderer with the options of its timed run."""
    seen = []
    real = benchmark.rasterize
    monkeypatch.setattr(benchmark, "rasterize", lambda *a, options=None, **k: seen.append(options) or real(
        *a, options=options, **k))
    monkeypatch.setattr(benchmark, "kernel_breakdown", lambda fn, *args: fn() and {"kernel": 1.0})
    options = benchmark.parse_options("tile_size=8,color_storage=float16")
    variant = benchmark.parse_variant("cap:capture=true", options)
    row = benchmark.benchmark_scene("random", 50, 16, 16, "cpu", options, [variant], warmup=0, runs=1,
                                    breakdown=True)
    assert row["breakdown_ms"] == {"ours": {"kernel": 1.0}, "cap": {"kernel": 1.0}}
    # Timed forward and forward+backward of each, the count render of ours, the gradients of ours and
    # the variant (compared), then each one's breakdown.
    assert seen == [options] * 2 + [variant[1]] * 2 + [options] * 2 + [variant[1], options, variant[1]]
    table = benchmark.benchmark_table([row], "t")
    assert "| random | 50 | cap |" in table and "Per-kernel GPU time, random 50, cap" in table
