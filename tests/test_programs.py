"""Programs: one kernel per skinning program, the kernels' arguments as warm_up reads them,
and warm_up's empty launches (a program prefetched, a worker standing)."""
from __future__ import annotations

import numpy as np
import pytest
from launches import standing_workers_or_skip

from nrpose import device, diagnostics
from nrpose.errors import DeviceError, InputError
from nrpose.pose import skinning
from nrpose.pose.mls import kernel_options, lanes_for

#: every program the deformers build, as (kernel file, build options)
PROGRAMS = [*skinning.PROGRAMS.values(), ("nrmls.cl", kernel_options(lanes_for(9), 0, 9, 8, "weight", True, False)),
            ("nrmls.cl", kernel_options(lanes_for(0), 5, 0, 0, "weight", False, True)), ("global_fit.cl", ())]


@pytest.mark.parametrize("name,options", PROGRAMS)
def test_kernel_arguments_match_the_built_kernels(name, options):
    """kernel_arguments (read from the source) names every kernel of the program with its
    argument count, and marks as pointers exactly the arguments declared with `*`."""
    prg = device.program(name, options)
    found = device.kernel_arguments(device.kernel_source(name))
    for kernel in prg.all_kernels():
        assert len(found[kernel.function_name]) == kernel.num_args
    assert found.get("lbs") in (None, (True,) * 6 + (False,) * 4 + (True, False))


@pytest.mark.parametrize("method", sorted(skinning.PROGRAMS))
def test_a_skinning_program_holds_its_method_kernel_alone(method):
    skinning.prefetch_program(method)
    prg = device.program(*skinning.PROGRAMS[method])
    assert [k.function_name for k in prg.all_kernels()] == [method]


def test_skinning_program_needs_a_kernel_chosen():
    with pytest.raises(DeviceError, match="(?s)skinning.cl.*LBS_KERNEL"):
        device.program("skinning.cl", ("-DNO_KERNEL_CHOSEN",))
    with pytest.raises(InputError, match="skinning method"):
        skinning.prefetch_program("nrmls")


def test_warm_up_ends_a_standing_worker_and_poses_stay_right():
    """warm_up while a deformer's worker stands (it polls the worker device): the worker is
    ended, the empty launches return, and the deformer poses the same frames after; a
    prefetch of a program built already launches nothing."""
    standing_workers_or_skip()
    rng = np.random.default_rng(3)
    n, j = 4000, 6
    rest = rng.normal(size=(n, 3))
    joints = rng.integers(0, j, size=(n, 2))
    weights = rng.random((n, 2)) + 0.05
    mats = np.tile(np.eye(4), (j, 1, 1))
    mats[:, :3, 3] = rng.normal(size=(j, 3))
    lbs = skinning.LbsSkinner(rest, joints, weights)
    device.set_standby_s(0.5)
    try:
        before = lbs.pose(mats)
        diagnostics.relaunch(lbs, workers=True)     # its worker stands
        assert device.standing_mailbox() is lbs._jobs
        skinning.prefetch_program("lbs")        # built already: no launch, the worker stands on
        assert device.standing_mailbox() is lbs._jobs
        device.warm_up(device.program(*skinning.PROGRAMS["dqs"]), device.kernel_source("skinning.cl"))
        assert device.standing_mailbox() is None
        assert np.array_equal(lbs.pose(mats), before)
        assert np.abs(before - skinning.lbs_reference(rest, joints, weights, mats)).max() < 1e-5 * np.abs(rest).max()
    finally:
        device.set_standby_s(None)
