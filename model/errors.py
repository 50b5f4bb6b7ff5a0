"""The one base class for errors a user can cause (bad file, field, spec or setting).

The command line and the service catch `UserInputError` at the edge and show its one-line message;
everything else is a bug and propagates with its traceback.
"""


class UserInputError(ValueError):
    """Bad input from a user, a file, the bus or the serial line; the message names what and where."""
