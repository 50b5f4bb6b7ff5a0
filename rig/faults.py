"""Device faults and safety trips: the second of hdrig's three kinds of error.

- Bad input from a user, a file, the bus or the serial line is a `model.errors.UserInputError`: one
  line, exit status 2, HTTP 4xx.
- A device fault or a safety trip while the rig works (a drive fault, a lost heartbeat, a SYNC nobody
  answered, a DAQ that stopped streaming) is a `DeviceFaultError`: the rig quick-stops, the run ends
  `aborted: <fault>` with its data, the command exits with status 3 and the service reports the run
  aborted. It is not the user's fault and not a bug.
- Anything else is a bug: not caught, not hidden.
"""


class DeviceFaultError(RuntimeError):
    """The bench failed while working: the message says which device and what it reported."""


class StorageFaultError(DeviceFaultError):
    """The run store could not write (disk full, file too large, read-only): the rows already on disk are
    kept, the run ends `aborted: <what the disk said>`."""
