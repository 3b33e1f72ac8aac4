"""Training: losses, learning-rate schedules, the shared loop and the Scaffold-GS and 3DGS trainers."""
from ..config import TrainConfig
from ..strategies import ScaffoldStrategy
from .losses import photometric_loss, psnr, ssim, volume_loss
from .base import ViewTrainer
from .gaussians import GaussianTrainer
from .trainer import ScaffoldTrainer

__all__ = ["GaussianTrainer", "ScaffoldStrategy", "ScaffoldTrainer", "ViewTrainer", "TrainConfig", "photometric_loss", "psnr", "ssim", "volume_loss"]
