"""SecureGS: private decoders, payloads, region-aware density optimization, containers and keys."""
from .heads import PrivateHeads
from .payload import Payload, PayloadSpec, build_payload
from .strategy import MODES, RegionAwareStrategy
from .trainer import HIDDEN_FEATURE_GRAD, SecureTrainer

__all__ = ["HIDDEN_FEATURE_GRAD", "MODES", "Payload", "PayloadSpec", "PrivateHeads", "RegionAwareStrategy",
           "SecureTrainer", "build_payload"]
