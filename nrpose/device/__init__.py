"""OpenCL on PoCL's CPU devices: the context, programs, host memory, and launches that
the calling thread shares with PoCL's worker threads through a job mailbox.

Modules: :mod:`~nrpose.device.env` (PoCL settings, context, queues),
:mod:`~nrpose.device.programs` (kernel sources and builds), :mod:`~nrpose.device.memory`
(host arrays, frame arrays, handoff slots), :mod:`~nrpose.device.policy` (when launches
share, the standby of standing workers), :mod:`~nrpose.device.mailbox` (the job mailbox,
:class:`Jobs`), :mod:`~nrpose.device.launch` (:func:`launch_shared`),
:mod:`~nrpose.device.timing` (profiling and spans), :mod:`~nrpose.device.bound`
(:class:`BoundKernel`, the base of the deformers). Their public names are importable
from here.
"""
from .bound import BoundKernel, run_coded_rows
from .env import (INSTALL_HINT, context, describe, fine_grain_svm, may_pin_workers, plain_opencl,
                  pocl_cpu_context, pocl_environment, pocl_settings, pyopencl, usable_cpus, whole_job, work_items,
                  worker_device, worker_queue, WHOLE_JOB_VARIABLE)
from .launch import launch_shared
from .mailbox import (ENDS_MAX_BOUND_BYTES, JOB_CLOSED, JOB_DESC, JOB_DESCS, JOB_DONE, JOB_END_BITS,
                      JOB_ENDS_MAX_BLOCKS, JOB_IN_PROLOGUE, JOB_INTS, JOB_NEXT, JOB_PROLOGUE, JOB_QUIT,
                      JOB_STANDING, JOB_TAG_SHIFT, ROLE_CALLER, ROLE_PROLOGUE, STANDING_MIN_BLOCKS, STANDING_RUN,
                      STANDING_YIELD_S, Jobs, calibrate_standby)
from .memory import HANDOFF_SLOTS, Handoff, HostArray, check_out_writable, frame_array, frame_count, frames_in
from .policy import (SHARE_MIN_S, STANDBY_MAX_S, STANDBY_S, set_standby_s, standby_s, standing_mailbox,
                     standing_workers_possible, stop_standing, time_alone, worth_sharing)
from .programs import (WARM_UP_BYTES, build_source, kernel_arguments, kernel_source, prefetch, program,
                       program_options, warm_up, with_headers)
from .timing import (EVENT_CLOCK, event_clock_ns, events_span_s, profiling_queues, published_span_s,
                     timing_queue)

__all__ = [name for name in dir() if not name.startswith("_") and name not in
           ("bound", "env", "launch", "mailbox", "memory", "policy", "programs", "timing")]
