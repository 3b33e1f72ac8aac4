"""Probe: how often a random key leaves a bit of the message without voters after a random half of
the anchors is cut, on the scene of tests/test_secure.py::test_bits_are_read_from_the_anchor_features
(docs/results.md, "Keys that leave a bit without voters after a half-cut"). For each bit grid
(``--bit-cell-voxels``), KEYS fresh keys and messages of 16 bits over the scene's anchors; the same
seeded half as the test. No training: a bit's voters depend on the key and the positions only.

    python docs/probes/half_cut_voters.py [KEYS]
"""
import random
import sys

import torch

from securegs_warp.cli.common import quiet_warp
from securegs_warp.data import make_synthetic_scene
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure import SecureConfig, SecureTrainer
from securegs_warp.secure.keyed_bits import KeyedBitDecoder, new_seed
from securegs_warp.train import TrainConfig

quiet_warp()
keys = int(sys.argv[1]) if len(sys.argv) > 1 else 2000
scene = make_synthetic_scene(hidden="mug", level="object", width=40, height=30, n_train=6, n_test=2, n_points=600)
draw = random.Random(0)
for voxels in (16.0, 4.0):
    trainer = SecureTrainer(scene, TrainConfig(iterations=1, raster=RasterOptions(tile_size=8), densify=False),
                            SecureConfig(payload="bits:16", bit_cell_voxels=voxels))
    xyz, feat_dim = trainer.model.anchors.xyz, trainer.model.anchors.feat.shape[1]
    cell = trainer.model.private.bits.cell
    half = torch.randperm(len(xyz), generator=torch.Generator().manual_seed(0))[: len(xyz) // 2]
    empty = 0
    for _ in range(keys):
        message = "".join(draw.choice("01") for _ in range(16))
        bits = KeyedBitDecoder(feat_dim, message, new_seed(), cell).anchor_bits(xyz[half])
        empty += int((torch.bincount(bits, minlength=16) == 0).any())
    print(f"{voxels:g}-voxel grid, {len(xyz)} anchors: {empty} of {keys} keys leave a bit without voters "
          f"after the half-cut ({empty / keys:.2%})")
