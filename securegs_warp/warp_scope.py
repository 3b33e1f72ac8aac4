"""``WarpScope``: Warp's device and, on CUDA, torch's current stream, for the kernels launched
on torch tensors (the rasterizer's, the SSIM's), so that Warp's work is ordered with torch's."""
import torch
import warp as wp


class WarpScope:
    """``with``: Warp's device and (on CUDA) torch's current stream."""

    def __init__(self, device, torch_device: torch.device):
        self.scopes = [wp.ScopedDevice(device)]
        if torch_device.type == "cuda":
            self.scopes.append(wp.ScopedStream(wp.stream_from_torch(torch_device)))

    def __enter__(self):
        for s in self.scopes:
            s.__enter__()

    def __exit__(self, *exc):
        for s in reversed(self.scopes):
            s.__exit__(*exc)
