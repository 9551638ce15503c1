"""Ways a shared launch may split its blocks (nrpose.device.launch_shared), for tests
that check every split gives the same result, and the skip of tests that need a
standing worker."""
import pytest

from nrpose import device, diagnostics


def standing_workers_or_skip() -> None:
    """Skip the calling test where no worker can stand: no PoCL worker device with shared
    memory (launches then run on one queue), or not an x86 host
    (:func:`nrpose.device.standing_workers_possible`)."""
    if device.worker_queue() is None or not device.fine_grain_svm():
        pytest.skip("no PoCL worker device with shared memory here: launches run on one queue")
    if not device.standing_workers_possible():
        pytest.skip("standing workers only on x86 hosts")


def splits() -> dict[str, dict]:
    """``{name: relaunch keyword arguments, plus "standby_us"}``: the calling thread
    alone, shared with a standing worker, shared with workers woken for the launch, and
    (where the context has PoCL's worker device) the workers alone. Run them with
    :func:`relaunch`."""
    runs = {"alone": {"workers": False},
            "standing worker": {"workers": True, "standby_us": "1000"},
            "woken workers": {"workers": True, "standby_us": "0"}}
    wq = device.worker_queue()
    if wq is not None:
        runs["workers only"] = {"queues": (None, wq)}
    return runs


def relaunch(deformer, split: dict, monkeypatch) -> None:
    """``diagnostics.relaunch(deformer)`` as ``split`` (a value of :func:`splits`) says, twice: a
    standing worker started by the first launch serves the second."""
    kw = dict(split)
    monkeypatch.setattr(device.policy, "_STANDBY", [None])           # restored after the test
    device.set_standby_s(float(kw.pop("standby_us", "1000")) * 1e-6)
    diagnostics.relaunch(deformer, **kw)
    diagnostics.relaunch(deformer, **kw)
