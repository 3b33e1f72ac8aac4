"""Training: losses, learning-rate schedules, densification strategies and the trainer."""
from .losses import photometric_loss, psnr, ssim, volume_loss
from .strategy import ScaffoldStrategy
from .trainer import ScaffoldTrainer, TrainConfig, render_fps

__all__ = ["ScaffoldStrategy", "ScaffoldTrainer", "TrainConfig", "photometric_loss", "psnr",
           "render_fps", "ssim", "volume_loss"]
