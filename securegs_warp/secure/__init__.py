"""SecureGS: private decoders, payloads, the secure model and trainer, containers and keys."""
from ..config import SecureConfig
from .heads import PrivateHeads
from .model import SecureModel
from .payload import Payload, PayloadSpec, build_payload
from .trainer import SecureTrainer

__all__ = ["Payload", "PayloadSpec", "PrivateHeads", "SecureConfig", "SecureModel", "SecureTrainer", "build_payload"]
