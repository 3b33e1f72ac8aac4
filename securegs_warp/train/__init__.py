"""Training: losses, learning-rate schedules and the Scaffold-GS trainer."""
from ..config import TrainConfig
from ..strategies import ScaffoldStrategy
from .losses import photometric_loss, psnr, ssim, volume_loss
from .trainer import ScaffoldTrainer

__all__ = ["ScaffoldStrategy", "ScaffoldTrainer", "TrainConfig", "photometric_loss", "psnr", "ssim", "volume_loss"]
