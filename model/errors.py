"""The one base class for errors a user can cause (bad file, field, spec or setting).

The command line and the service catch `UserInputError` at the edge and show its one-line message;
everything else is a bug and propagates with its traceback.
"""

from pydantic import ValidationError


class UserInputError(ValueError):
    """Bad input from a user, a file, the bus or the serial line; the message names what and where."""


def describe_validation_error(exc: ValidationError) -> str:
    """The first error of a pydantic validation as `field 'a.b': what is wrong (got value)`."""
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"]) or "(top level)"
    msg = err["msg"].removeprefix("Value error, ")
    value = err.get("input")
    shown = "" if isinstance(value, dict | list) or value is None else f" (got {value!r})"
    more = f" [+{exc.error_count() - 1} more]" if exc.error_count() > 1 else ""
    return f"field '{where}': {msg}{shown}{more}"
