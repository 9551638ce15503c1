"""Ways a shared launch may split its blocks (nrpose.device.launch_shared), for tests
that check every split gives the same result."""
from nrpose import device


def splits() -> dict[str, dict]:
    """``{name: relaunch keyword arguments}``: the calling thread alone, shared, and (where
    the context has PoCL's worker device) the workers alone."""
    runs = {"alone": {"workers": False}, "shared": {"workers": True}}
    wq = device.worker_queue()
    if wq is not None:
        runs["workers only"] = {"queues": (None, wq)}
    return runs
