"""Registers of the CUDA blending backward, from NVRTC cubins (no GPU needed): the
``backward_max_registers`` cap reaches the compiled kernel, and the cubin reader reads what it
claims to. Skipped where Warp was built without NVRTC for sm_90."""
import pytest
import warp as wp

from securegs_warp.cuda_resources import (cubin_resources, kernel_barriers, kernel_resources, ptx_barriers,
                                          ptx_warp_traffic)
from securegs_warp.kernels.blend import blend_kernels
from securegs_warp.rasterizer import RasterOptions

wp.init()
_runtime = wp._src.context.runtime
nvrtc = pytest.mark.skipif(not (_runtime.is_cuda_enabled and 90 in (_runtime.nvrtc_supported_archs or ())),
                           reason="Warp without NVRTC for sm_90")


def backward(max_registers=0, fast_math=False, pixels=1):
    return blend_kernels(3, 16, False, 256, True, "float32", fast_math, True, max_registers, packed=False,
                         backward_pixels=pixels)[1]


@nvrtc
def test_packed_records_take_barriers_out_of_the_batch_loop():
    # Per batch, "fields" pays two barriers per load into shared memory (one before the tile is
    # overwritten, one after): ids, means2d, conics, opacities, colours (and depths). "packed" pays
    # one after the ids and one after the records, the backward one more before overwriting the ids
    # its walk reads; the forward's 4 more are its "all pixels done" vote.
    for depth in (False, True):
        fields, packed = (blend_kernels(3, 16, depth, 256, True, "float32", False, packed=p) for p in (False, True))
        per_batch = [kernel_barriers(k)["loop_barriers"] for k in (*fields, *packed)]
        assert per_batch == [14 + 2 * depth, 10 + 2 * depth, 6, 3]


def test_ptx_barrier_counter_finds_the_innermost_loop():
    ptx = "\n".join(["bar.sync 0;", "$L__A:", "bar.sync 0;", "$L__B:", "bar.sync 0;", "barrier.sync 0;",
                     "$L__C:", "add.s32 %r1, %r1, 1;", "@%p1 bra $L__C;", "@%p2 bra $L__B;",
                     "@%p3 bra.uni $L__A;", "ret;"])
    assert ptx_barriers(ptx) == {"barriers": 4, "loop_barriers": 2}
    with pytest.raises(ValueError, match="separate loops"):
        ptx_barriers("$L__A:\nbar.sync 0;\n@%p1 bra $L__A;\n$L__B:\nbar.sync 0;\n@%p1 bra $L__B;")


def test_ptx_warp_traffic_counts_shuffles_and_global_atomics():
    ptx = "\n".join(["shfl.sync.bfly.b32 %r2|%p1, %r1, 16, 31, -1;", "shfl.sync.idx.b32 %r3, %r1, 0, 31, -1;",
                     "atom.global.add.f32 %f1, [%rd1], %f2;", "red.global.add.f32 [%rd2], %f3;",
                     "atom.shared.add.u32 %r4, [%r5], 1;", "ld.global.f32 %f4, [%rd3];"])
    assert ptx_warp_traffic(ptx) == {"shuffles": 2, "atomics": 2}


@nvrtc
@pytest.mark.parametrize("pixels,cap", [(1, 64), (2, 80)])
def test_register_cap_reaches_the_compiled_backward(pixels, cap):
    free, capped = kernel_resources(backward(pixels=pixels)), kernel_resources(backward(cap, pixels=pixels))
    assert free["registers"] > cap  # the cap binds: the compiler's choice uses more
    assert capped["registers"] <= cap
    # Spilling is the price, and a small one: a few words a thread, not the kernel's state.
    assert free["frame_bytes"] == 0 and capped["frame_bytes"] <= 64


@nvrtc
@pytest.mark.parametrize("channels,depth", [(1, False), (3, False), (26, True)])
def test_gradient_scatter_compiles_for_every_row_width(channels, depth):
    # Rows of 7, 9 and 33 words: padded to 8 and 16 values, and split into chunks of 32 and 1.
    kernel = blend_kernels(channels, 16, depth, 256, True, "float32", True, packed=True, backward_pixels=2)[1]
    assert kernel_resources(kernel)["registers"] > 0


def test_cap_is_validated():
    assert RasterOptions(backward_max_registers=64).backward_max_registers == 64
    for bad in (16, 256, -1):
        with pytest.raises(ValueError, match="backward_max_registers"):
            RasterOptions(backward_max_registers=bad)


def test_cubin_reader_refuses_what_is_not_a_cubin():
    with pytest.raises(ValueError, match="ELF"):
        cubin_resources(b"not an elf file at all, just some bytes")
