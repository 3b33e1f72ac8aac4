"""Probe: three procedural meshes the project had never hidden, written as OBJ files for
`scripts/hiding_study.py` (docs/results.md, "Six more at the demo's budget: three shapes made here,
a scanned mesh and two built-ins at new seeds"). Each stresses the anchor cloud differently: a
chair's thin legs (little surface, much empty space), an upright ring (a hole the cover shows
through) and a lumpy blob (a closed surface with no flat part).

    python docs/probes/new_shapes.py OUT_DIR     # writes chair.obj, ring.obj, blob.obj
"""
import sys
from pathlib import Path

import numpy as np
import trimesh
from trimesh.creation import box, cylinder, icosphere, torus

from securegs_warp.io.atomic import atomic_write

if len(sys.argv) != 2:
    raise SystemExit("usage: python docs/probes/new_shapes.py OUT_DIR")
out = Path(sys.argv[1])
out.mkdir(parents=True, exist_ok=True)


def export(mesh, name):
    atomic_write(out / name, lambda f: mesh.export(f, file_type="obj"))


parts = [box((1, 1, 0.1)).apply_translation((0, 0, 0.5)), box((1, 0.1, 1)).apply_translation((0, 0.45, 1.0))]
for x in (-0.42, 0.42):
    for y in (-0.42, 0.42):
        parts.append(cylinder(radius=0.05, height=0.5, sections=12).apply_translation((x, y, 0.25)))
export(trimesh.util.concatenate(parts), "chair.obj")
upright = trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0))
export(torus(major_radius=0.5, minor_radius=0.12).apply_transform(upright), "ring.obj")
blob = icosphere(subdivisions=4, radius=0.5)
v = blob.vertices
bump = 0.08 * np.sin(6 * v[:, 0]) * np.cos(5 * v[:, 1]) + 0.05 * np.sin(9 * v[:, 2])
blob.vertices = v + blob.vertex_normals * bump[:, None]
export(blob, "blob.obj")
