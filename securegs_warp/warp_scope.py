"""``WarpScope``: Warp's device and, on CUDA, torch's current stream, for the kernels launched
on torch tensors (the rasterizer's, the SSIM's), so that Warp's work is ordered with torch's."""
import torch
import warp as wp


# (torch device, stream handle) -> Warp's wrapper of that stream, kept for as long as the process
# runs. A wrapper that is garbage-collected unregisters its CUDA stream from Warp, and with it any
# capture Warp was told of on that stream (secure.hidden_graph's); one wrapper per stream also saves
# making one per scope. Torch keeps a small pool of streams, so this stays small.
_WARP_STREAMS: dict = {}


def warp_stream(stream_or_device) -> wp.Stream:
    """Warp's wrapper of a torch CUDA stream (a ``torch.cuda.Stream``, or a torch device for its
    current stream), the same object for the same stream."""
    stream = stream_or_device if isinstance(stream_or_device, torch.cuda.Stream) \
        else torch.cuda.current_stream(stream_or_device)
    key = (stream.device, stream.cuda_stream)  # the default stream's handle is 0 on every device
    wrapper = _WARP_STREAMS.get(key)
    if wrapper is None:
        wrapper = _WARP_STREAMS[key] = wp.stream_from_torch(stream)
    return wrapper


class WarpScope:
    """``with``: Warp's device and (on CUDA) torch's current stream."""

    def __init__(self, device, torch_device: torch.device):
        self.scopes = [wp.ScopedDevice(device)]
        if torch_device.type == "cuda":
            # Entering waits for Warp's previous stream (an event recorded there). Inside torch's
            # graph capture (secure.hidden_graph) that wait would tie the graph to work outside it;
            # everything the graph orders after is on the capturing stream already.
            sync = not torch.cuda.is_current_stream_capturing()
            self.scopes.append(wp.ScopedStream(warp_stream(torch_device), sync_enter=sync))

    def __enter__(self):
        for s in self.scopes:
            s.__enter__()

    def __exit__(self, *exc):
        for s in reversed(self.scopes):
            s.__exit__(*exc)
