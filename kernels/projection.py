"""EWA projection of 3D Gaussians through a pinhole camera (gsplat 1.5 classic conventions).

One thread per Gaussian. Warp generates the adjoint of this kernel; it is recorded on the render's
tape, so gradients reach means, quats, scales and opacities through it.

Numerical choices (each keeps a hard case finite and close to the float64 reference):
- The rigid world-to-camera transform runs in float64: with coordinates of magnitude 1e4 a float32
  transform loses ~1e-3 in camera space, far more than the 1e-4 image tolerance.
- The 2D covariance is built from its square root A = J·W·R·S (2×3), so det(AAᵀ) = |a0 × a1|²
  (Lagrange's identity) is never negative, even for anisotropy 1e6 where c00·c11 − c01² cancels.
- The antialiasing ratio det(Σ)/det(Σ + εI) is taken in float64: it stays finite for screen-space
  deviations whose determinants overflow float32.
- Quaternions are normalised with a floor on their norm: a zero quaternion gives the identity
  rotation and finite gradients instead of NaN.
"""
import functools

import warp as wp

from .records import (COLOR_STORAGES, R_BOX, R_COLOR, R_CONIC, R_DEPTH, R_OPACITY, R_XY, blend_box, colors_in_record,
                      record_width)

# Radius rules (compile-time): how far from its centre a 2D Gaussian is allowed to reach.
RADIUS_RULES = ("opacity_aware", "3sigma")
_OPACITY_AWARE, _THREE_SIGMA = 0, 1

QUAT_NORM_FLOOR = 1.0e-12


@wp.func
def quat_to_rotmat(q: wp.vec4) -> wp.mat33:
    """w-first quaternion (not necessarily normalised) → rotation matrix."""
    # Floor the squared norm, not the norm: sqrt's derivative at 0 would be inf (NaN gradients).
    inv = 1.0 / wp.sqrt(wp.max(wp.dot(q, q), QUAT_NORM_FLOOR * QUAT_NORM_FLOOR))
    w = q[0] * inv
    x = q[1] * inv
    y = q[2] * inv
    z = q[3] * inv
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@functools.lru_cache(maxsize=None)
def projection_kernel(antialiased: bool, radius_rule: str, fast_math: bool, record: tuple | None = None):
    """The projection kernel specialised for one option set.

    antialiased: multiply opacity by the Mip-Splatting compensation sqrt(det(Σ)/det(Σ + εI)).
    radius_rule: "opacity_aware" (gsplat 1.5: per-axis, extent min(3.33, sqrt(2 ln(o/α_min)))),
        "3sigma" (original 3DGS: square, 3·sqrt(λ_max), no opacity test). The opacity-aware extent
        along each axis is already the ellipse's exact one (e·sqrt(Σ_xx)), so no tighter rule exists.
    fast_math: compile with Warp's ``fast_math`` module option (CUDA: nvcc ``--use_fast_math``,
        approximate exp/log/sqrt/division and flushed denormals; the float64 camera transform is
        unaffected). Warp 1.19 does not pass it to its CPU compiler: there it changes nothing.
    record: (C, color_storage): also write each visible Gaussian's packed record (layout in
        ``kernels/records.py``) into ``records`` [N, record_width / 2] int64 (each word the bits of
        two float32 words of the row), with its C colours from
        ``colors`` [N, C] of ``color_storage`` when ``colors_in_record``; None: neither array is
        used (pass None for both). Written here rather than by a kernel of its own, which read back
        the outputs just written (a launch and a pass over N rows more). The records take no gradient.
    """
    if radius_rule not in RADIUS_RULES:
        raise ValueError(f"radius_rule must be one of {RADIUS_RULES}, got {radius_rule!r}")
    rule = RADIUS_RULES.index(radius_rule)
    PACK = record is not None
    C, color_storage = record if PACK else (1, "float32")
    ColorT = COLOR_STORAGES[color_storage]
    WITH_COLORS = PACK and colors_in_record(color_storage)
    W = record_width(C, color_storage)
    Row = wp.types.vector(length=W, dtype=wp.float32)

    @wp.func
    def write_record(records: wp.array2d(dtype=wp.int64), colors: wp.array2d(dtype=ColorT), i: int, xy: wp.vec2,
                     conic: wp.vec3, opacity: float, depth: float, alpha_min: float):
        """Row i of ``records``: zero-initialised (the padding is gathered with the rest of the
        row), stored 8 bytes at a time. A warp's stores land a row's stride apart, so each store
        instruction touches a memory sector per thread: 8-byte stores touch half as many as
        float32 ones (Warp's vec4 stores are four float32 stores)."""
        r = Row()
        r[R_XY] = xy[0]
        r[R_XY + 1] = xy[1]
        r[R_CONIC] = conic[0]
        r[R_CONIC + 1] = conic[1]
        r[R_CONIC + 2] = conic[2]
        r[R_OPACITY] = opacity
        r[R_DEPTH] = depth
        box = blend_box(xy, conic, opacity, alpha_min)
        r[R_BOX] = box[0]
        r[R_BOX + 1] = box[1]
        if wp.static(WITH_COLORS):
            for c in range(C):
                r[R_COLOR + c] = float(colors[i, c])
        for q in range(W // 2):
            records[i, q] = wp.cast(wp.vec2(r[2 * q], r[2 * q + 1]), wp.int64)

    # The records take no gradient, and the generated adjoint kernel need not write them again
    # when it replays the forward: both are no-ops, so the record costs the backward nothing.
    @wp.func_grad(write_record)
    def adj_write_record(records: wp.array2d(dtype=wp.int64), colors: wp.array2d(dtype=ColorT), i: int,
                         xy: wp.vec2, conic: wp.vec3, opacity: float, depth: float, alpha_min: float):
        pass

    @wp.func_replay(write_record)
    def replay_write_record(records: wp.array2d(dtype=wp.int64), colors: wp.array2d(dtype=ColorT), i: int,
                            xy: wp.vec2, conic: wp.vec3, opacity: float, depth: float, alpha_min: float):
        pass

    def project(
        means: wp.array(dtype=wp.vec3),
        quats: wp.array(dtype=wp.vec4),
        scales: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        viewmat: wp.array(dtype=float),
        intrinsics: wp.array(dtype=float),
        colors: wp.array2d(dtype=ColorT),
        width: int,
        height: int,
        near: float,
        far: float,
        eps2d: float,
        alpha_min: float,
        radius_clip: float,
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        depths: wp.array(dtype=float),
        radii: wp.array(dtype=wp.vec2i),
        opacities_out: wp.array(dtype=float),
        records: wp.array2d(dtype=wp.int64),
    ):
        i = wp.tid()
        # viewmat: row-major world-to-camera 4×4; intrinsics: row-major K (3×3). Both are read on the
        # device, so a render copies nothing from the host.
        rot = wp.mat33d(wp.float64(viewmat[0]), wp.float64(viewmat[1]), wp.float64(viewmat[2]),
                        wp.float64(viewmat[4]), wp.float64(viewmat[5]), wp.float64(viewmat[6]),
                        wp.float64(viewmat[8]), wp.float64(viewmat[9]), wp.float64(viewmat[10]))
        trans = wp.vec3d(wp.float64(viewmat[3]), wp.float64(viewmat[7]), wp.float64(viewmat[11]))
        fx = intrinsics[0]
        fy = intrinsics[4]
        cx = intrinsics[2]
        cy = intrinsics[5]
        m = means[i]
        # float64 rigid transform (see module docstring), rounded once to float32.
        md = wp.vec3d(wp.float64(m[0]), wp.float64(m[1]), wp.float64(m[2]))
        cd = rot * md + trans
        x = wp.float32(cd[0])
        y = wp.float32(cd[1])
        z = wp.float32(cd[2])

        visible = z >= near and z <= far
        rx = float(0.0)
        ry = float(0.0)
        if visible:
            w_rot = wp.mat33(
                wp.float32(rot[0, 0]), wp.float32(rot[0, 1]), wp.float32(rot[0, 2]),
                wp.float32(rot[1, 0]), wp.float32(rot[1, 1]), wp.float32(rot[1, 2]),
                wp.float32(rot[2, 0]), wp.float32(rot[2, 1]), wp.float32(rot[2, 2]),
            )
            s = scales[i]
            # M = W·R·S: columns of the camera-space covariance square root.
            mm = w_rot * quat_to_rotmat(quats[i]) * wp.diag(s)

            # Perspective Jacobian, clamped outside a 1.3× frustum around the principal point.
            tan_fovx = 0.5 * float(width) / fx
            tan_fovy = 0.5 * float(height) / fy
            lim_x_pos = (float(width) - cx) / fx + 0.3 * tan_fovx
            lim_x_neg = cx / fx + 0.3 * tan_fovx
            lim_y_pos = (float(height) - cy) / fy + 0.3 * tan_fovy
            lim_y_neg = cy / fy + 0.3 * tan_fovy
            rz = 1.0 / z
            rz2 = rz * rz
            tx = z * wp.min(lim_x_pos, wp.max(-lim_x_neg, x * rz))
            ty = z * wp.min(lim_y_pos, wp.max(-lim_y_neg, y * rz))
            j0 = wp.vec3(fx * rz, 0.0, -fx * tx * rz2)
            j1 = wp.vec3(0.0, fy * rz, -fy * ty * rz2)
            a0 = wp.transpose(mm) * j0  # row 0 of A = J·M
            a1 = wp.transpose(mm) * j1
            c00 = wp.dot(a0, a0)
            c01 = wp.dot(a0, a1)
            c11 = wp.dot(a1, a1)
            det_orig = wp.length_sq(wp.cross(a0, a1))
            b00 = c00 + eps2d
            b11 = c11 + eps2d
            det = det_orig + eps2d * (c00 + c11) + eps2d * eps2d

            opacity = opacities[i]
            if wp.static(antialiased):
                # The ratio in float64: past ~4e9 px of screen-space deviation both determinants
                # overflow float32, and inf / inf (and its adjoint) would be NaN.
                a0d = wp.vec3d(wp.float64(a0[0]), wp.float64(a0[1]), wp.float64(a0[2]))
                a1d = wp.vec3d(wp.float64(a1[0]), wp.float64(a1[1]), wp.float64(a1[2]))
                det_orig_d = wp.length_sq(wp.cross(a0d, a1d))
                e = wp.float64(eps2d)
                det_d = det_orig_d + e * (wp.float64(c00) + wp.float64(c11)) + e * e
                ratio = wp.float32(det_orig_d / det_d)
                opacity = opacity * wp.sqrt(wp.max(ratio, 0.0) + 1.0e-30)

            if det > 0.0:
                if wp.static(rule == _THREE_SIGMA):
                    half_tr = 0.5 * (b00 + b11)
                    lam = half_tr + wp.sqrt(wp.max(0.1, half_tr * half_tr - det))
                    rx = wp.ceil(3.0 * wp.sqrt(lam))
                    ry = rx
                else:
                    if opacity >= alpha_min:
                        # At opacity == alpha_min the log is 0, and sqrt's adjoint there is
                        # 0 / 0 = NaN even though the radius passes no gradient back (it is
                        # rounded): feed sqrt a floored copy and keep the exact 0 in the forward.
                        log_ratio = 2.0 * wp.log(opacity / alpha_min)
                        extend = wp.where(log_ratio > 0.0,
                                          wp.min(3.33, wp.sqrt(wp.max(log_ratio, 1.0e-30))), 0.0)
                        rx = wp.ceil(extend * wp.sqrt(b00))
                        ry = wp.ceil(extend * wp.sqrt(b11))
            u = fx * x * rz + cx
            v = fy * y * rz + cy
            # Bound the radius so that it fits an int32; tile ranges are clamped to the image anyway.
            rx = wp.min(rx, 1.0e9)
            ry = wp.min(ry, 1.0e9)
            if rx <= radius_clip and ry <= radius_clip:
                rx = 0.0
                ry = 0.0
            if u + rx <= 0.0 or u - rx >= float(width) or v + ry <= 0.0 or v - ry >= float(height):
                rx = 0.0
                ry = 0.0
            if rx > 0.0:
                conic = wp.vec3(b11 / det, -c01 / det, b00 / det)
                means2d[i] = wp.vec2(u, v)
                conics[i] = conic
                depths[i] = z
                opacities_out[i] = opacity
                if wp.static(PACK):
                    write_record(records, colors, i, wp.vec2(u, v), conic, opacity, z, alpha_min)
        if rx > 0.0:
            radii[i] = wp.vec2i(int(rx), int(ry))
        else:
            # Every row of these outputs is written, so no render clears them first (a pass over N
            # rows of four arrays, where culled Gaussians are usually few). A culled row's record
            # is never gathered and stays unwritten.
            radii[i] = wp.vec2i(0, 0)
            means2d[i] = wp.vec2(0.0, 0.0)
            conics[i] = wp.vec3(0.0, 0.0, 0.0)
            depths[i] = 0.0
            opacities_out[i] = 0.0

    tag = (f"{'aa' if antialiased else 'classic'}_{radius_rule}{'_fast' if fast_math else ''}"
           f"{f'_rec{C}_{color_storage}' if PACK else ''}")
    project.__name__ = project.__qualname__ = f"project_{tag}"
    # fast_math is a module option: each variant gets its own module.
    return wp.kernel(project, module="unique", module_options={"fast_math": fast_math})
