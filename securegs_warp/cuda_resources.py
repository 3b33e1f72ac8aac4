"""Registers and local-memory frame of a Warp kernel compiled for a CUDA architecture, read from the
cubin that NVRTC produces: no GPU is needed (Warp compiles ahead of time with ``compile_aot_module``).

``kernel_barriers`` counts the block barriers in the kernel's PTX, in all and in its innermost loop
that holds any (the blending kernels' walk over batches of Gaussians); ``ptx_warp_traffic`` its warp
shuffles and global atomics.

Occupancy follows from the registers: an H100 multiprocessor holds 65,536 registers, allocated per
warp in multiples of 256 (8 per thread), so blocks of 256 threads fit 2 per multiprocessor at 81–128
registers a thread, 3 at 73–80 and 4 at ≤ 64. A frame of more than 0 bytes means spilled registers
or a local array.
"""
from __future__ import annotations

import re
import struct
import tempfile

import warp as wp

# .nv.info attribute ids (CUDA's EIATTR_*), each with a (kernel symbol index, value) payload.
_EIATTR = {0x2F: "registers", 0x11: "frame_bytes"}
_EIFMT_NVAL, _EIFMT_BVAL, _EIFMT_HVAL, _EIFMT_SVAL = 1, 2, 3, 4


def _sections(elf: bytes) -> dict[str, bytes]:
    """Section name -> contents of a 64-bit little-endian ELF file."""
    if elf[:4] != b"\x7fELF" or elf[4] != 2:
        raise ValueError("not a 64-bit ELF file")
    shoff = struct.unpack_from("<Q", elf, 0x28)[0]
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", elf, 0x3A)
    headers = [struct.unpack_from("<IIQQQQ", elf, shoff + i * shentsize) for i in range(shnum)]
    names_at = headers[shstrndx][4]

    def name(offset):
        start = names_at + offset
        return elf[start:elf.index(b"\0", start)].decode()

    return {name(h[0]): elf[h[4]:h[4] + h[5]] for h in headers}


def _attributes(data: bytes):
    """(attribute id, kernel symbol index, value) of each (index, value) entry of a .nv.info section."""
    p = 0
    while p < len(data):
        fmt, attr = data[p], data[p + 1]
        if fmt == _EIFMT_SVAL:
            size = struct.unpack_from("<H", data, p + 2)[0]
            if size == 8:
                yield (attr, *struct.unpack_from("<II", data, p + 4))
            p += 4 + size
        elif fmt in (_EIFMT_NVAL, _EIFMT_BVAL, _EIFMT_HVAL):  # 4 bytes, value inline
            p += 4
        else:
            raise ValueError(f"unknown .nv.info attribute format {fmt} at byte {p}")


def cubin_resources(cubin: bytes) -> dict[str, int]:
    """{"registers", "frame_bytes"} of the one kernel of ``cubin`` (the global .nv.info section's
    entries). Raises ValueError when the file is not an ELF cubin or holds several kernels."""
    info = _sections(cubin).get(".nv.info")
    if info is None:
        raise ValueError("the cubin has no .nv.info section")
    found: dict[str, dict[int, int]] = {}
    for attr, kernel, value in _attributes(info):
        if attr in _EIATTR:
            found.setdefault(_EIATTR[attr], {})[kernel] = value
    registers = found.get("registers", {})
    if len(registers) != 1:
        raise ValueError(f"expected the register count of one kernel, found {len(registers)}")
    (kernel, count), = registers.items()
    return {"registers": count, "frame_bytes": found.get("frame_bytes", {}).get(kernel, 0)}


def kernel_resources(kernel, arch: int = 90) -> dict[str, int]:
    """{"registers", "frame_bytes"} per thread of ``kernel`` (a ``wp.Kernel`` alone in its module,
    as ``module="unique"`` makes it) compiled for sm_``arch``. Needs Warp's NVRTC (any Warp build
    with CUDA support), not a GPU."""
    with tempfile.TemporaryDirectory() as folder:
        paths = wp.compile_aot_module(kernel.module, device=None, arch=arch, module_dir=folder, use_ptx=False)
        with open(paths[0], "rb") as f:
            return cubin_resources(f.read())


def ptx_barriers(ptx: str) -> dict[str, int]:
    """{"barriers": block barriers (``bar.sync``/``barrier.sync``) in ``ptx``, "loop_barriers": those
    of the innermost loop that holds any} of a PTX listing of one kernel. A loop is the span from a
    label to the last branch back to it; a loop holds a barrier when no loop inside it does.
    Raises ValueError when several innermost loops hold barriers (the count would be ambiguous)."""
    lines = ptx.splitlines()
    labels = {m.group(1): i for i, line in enumerate(lines) if (m := re.match(r"^(\$\w+):", line))}
    loops: dict[str, tuple[int, int]] = {}
    for i, line in enumerate(lines):
        m = re.search(r"\bbra(?:\.uni)?\s+(\$\w+);", line)
        if m and m.group(1) in labels and labels[m.group(1)] < i:
            loops[m.group(1)] = (labels[m.group(1)], i)
    barriers = [i for i, line in enumerate(lines) if re.search(r"\b(bar|barrier)\.sync\b", line)]
    innermost: dict[tuple[int, int], int] = {}
    for b in barriers:
        around = [span for span in loops.values() if span[0] < b < span[1]]
        if around:
            span = min(around, key=lambda s: s[1] - s[0])
            innermost[span] = innermost.get(span, 0) + 1
    leaves = [span for span in innermost
              if not any(other != span and span[0] <= other[0] and other[1] <= span[1] for other in innermost)]
    if len(leaves) > 1:
        raise ValueError(f"{len(leaves)} separate loops hold barriers")
    return {"barriers": len(barriers), "loop_barriers": innermost[leaves[0]] if leaves else 0}


def ptx_warp_traffic(ptx: str) -> dict[str, int]:
    """{"shuffles": warp shuffle instructions (``shfl.sync``), "atomics": global-memory atomic
    instructions (``atom.global``, ``red.global``)} in a PTX listing: what a warp-level reduction
    and its gradient scatter cost in instructions (each may serve several lanes at once)."""
    return {"shuffles": len(re.findall(r"\bshfl\.sync\b", ptx)),
            "atomics": len(re.findall(r"\b(?:atom|red)\.global\b", ptx))}


def kernel_ptx(kernel, arch: int = 90) -> str:
    """The PTX of ``kernel`` (alone in its module) compiled for sm_``arch`` (NVRTC, no GPU)."""
    with tempfile.TemporaryDirectory() as folder:
        paths = wp.compile_aot_module(kernel.module, device=None, arch=arch, module_dir=folder, use_ptx=True)
        with open(paths[0], encoding="utf-8", errors="replace") as f:
            return f.read()


def kernel_barriers(kernel, arch: int = 90) -> dict[str, int]:
    """``ptx_barriers`` of ``kernel`` (alone in its module) compiled to PTX for sm_``arch``."""
    return ptx_barriers(kernel_ptx(kernel, arch))
