"""The CUDA branch of the blending backward's ``gradient_scatter`` (kernels/blend.py), run by an
interpreter of its generated source: 32 lanes in lockstep, ``__shfl_xor_sync(x, d)`` reading lane ^ d.
CUDA tests run the kernel itself on a GPU; this checks the generator everywhere, for every row width
(one chunk padded to a power of two, several chunks of 32). Unknown source lines fail the test, so a
change to the generator must come with its interpretation here."""
import random
import re

import pytest

from securegs_warp.kernels.blend import gradient_scatter

LANES = range(32)


def cuda_lines(width: int) -> list[str]:
    snippet = gradient_scatter(width).native_snippet
    cuda = snippet[snippet.index("#if defined(__CUDA_ARCH__)"):snippet.index("#else")]
    return [line.strip() for line in cuda.splitlines()[1:] if line.strip()]


def run_warp(width: int, g: list[list[int]]) -> list[tuple[int, int]]:
    """(row index, value) of each atomic add the warp makes, lanes' inputs ``g`` [32][width]."""
    lines, pc = cuda_lines(width), 0
    v = idx = up = None
    writes = []
    while pc < len(lines):
        s, pc = lines[pc], pc + 1
        if s in ("{", "}", "#pragma unroll", "const int lane = threadIdx.x & 31;"):
            continue
        if r := re.fullmatch(r"float v\[(\d+)\];", s):
            v = [[None] * int(r[1]) for _ in LANES]
        elif r := re.fullmatch(r"v\[(\d+)\] = g\[(\d+)\];", s):
            for t in LANES:
                v[t][int(r[1])] = g[t][int(r[2])]
        elif r := re.fullmatch(r"v\[(\d+)\] = 0\.0f;", s):
            for t in LANES:
                v[t][int(r[1])] = 0
        elif s == "int idx = 0;":
            idx = [0] * 32
        elif r := re.fullmatch(r"\{ const bool up = \(lane & (\d+)\) != 0;", s):
            up = [(t & int(r[1])) != 0 for t in LANES]
        elif r := re.fullmatch(r"for \(int i = 0; i < (\d+); \+\+i\) \{", s):
            send = re.fullmatch(r"const float send = up \? v\[i\] : v\[i \+ (\d+)\];", lines[pc])
            keep = re.fullmatch(r"const float keep = up \? v\[i \+ (\d+)\] : v\[i\];", lines[pc + 1])
            trade = re.fullmatch(r"v\[i\] = keep \+ __shfl_xor_sync\(0xffffffff, send, (\d+)\);", lines[pc + 2])
            assert send and keep and trade and lines[pc + 3] == "}", lines[pc:pc + 4]
            pc += 4
            for i in range(int(r[1])):
                sent = [v[t][i] if up[t] else v[t][i + int(send[1])] for t in LANES]
                kept = [v[t][i + int(keep[1])] if up[t] else v[t][i] for t in LANES]
                for t in LANES:
                    v[t][i] = kept[t] + sent[t ^ int(trade[1])]
        elif r := re.fullmatch(r"if \(up\) idx \+= (\d+); \}", s):
            idx = [i + int(r[1]) * u for i, u in zip(idx, up)]
        elif r := re.fullmatch(r"v\[0\] \+= __shfl_xor_sync\(0xffffffff, v\[0\], (\d+)\);", s):
            old = [v[t][0] for t in LANES]
            for t in LANES:
                v[t][0] = old[t] + old[t ^ int(r[1])]
        elif r := re.fullmatch(r"if \(\(lane & (\d+)\) == 0 && idx < (\d+)\) "
                               r"wp::atomic_add\(wp::address\(grad, gid, (\d+) \+ idx\), v\[0\]\);", s):
            writes += [(int(r[3]) + idx[t], v[t][0]) for t in LANES if (t & int(r[1])) == 0 and idx[t] < int(r[2])]
        else:
            raise AssertionError(f"unrecognised line of the generated scatter: {s!r}")
    return writes


@pytest.mark.parametrize("width", [1, 2, 7, 9, 10, 16, 23, 32, 33, 47, 64, 65, 70])
def test_each_value_is_summed_over_the_warp_and_added_once(width):
    rng = random.Random(width)
    for _ in range(3):
        # Integers, so the sums are exact whatever the order of additions.
        g = [[rng.randint(-10**6, 10**6) for _ in range(width)] for _ in LANES]
        writes = run_warp(width, g)
        assert sorted(k for k, _ in writes) == list(range(width))
        assert dict(writes) == {k: sum(g[t][k] for t in LANES) for k in range(width)}
