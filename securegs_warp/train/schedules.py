"""Learning-rate schedules (3DGS's ``get_expon_lr_func``)."""
import math


def exponential_lr(lr_init: float, lr_final: float, max_steps: int, step: int) -> float:
    """Log-linear interpolation from ``lr_init`` at step 0 to ``lr_final`` at ``max_steps``."""
    if lr_init == 0.0 and lr_final == 0.0:
        return 0.0
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)
