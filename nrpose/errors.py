"""Typed errors. Every user mistake raises a subclass of :class:`NrposeError`.

The message names the problem and, where there is one, the fix. The CLI prints
the message as one line on stderr and exits with status 2.
"""


class NrposeError(ValueError):
    """Base class of every error caused by bad input or a missing prerequisite."""


class InputError(NrposeError):
    """Malformed or unusable geometry, handles, weights or options."""


class HandleError(InputError):
    """A handle set that cannot drive a deformation (shapes, NaN, zero length...)."""


class FileFormatError(InputError):
    """A file that cannot be read: wrong extension, truncated, corrupt or inconsistent."""


class DeviceError(NrposeError):
    """No usable OpenCL platform/device, or a kernel failed to build."""
