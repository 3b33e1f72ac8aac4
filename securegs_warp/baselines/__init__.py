"""The paper's baselines on this engine (plain 3DGS lives in ``securegs_warp.gaussians``):
3DGS + StegaNeRF (``steganerf``); GS-Hider (``gs_hider``); ``comparison`` runs them beside SecureGS."""
