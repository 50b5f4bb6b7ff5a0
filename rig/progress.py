"""The command line's progress bar: tqdm on stderr, with ETA, fed by the runner's `Progress` callback.

The runner reports `(label, fraction of the whole job done)`; the service passes its own callback of the
same shape. The bar switches itself off when stderr is not a terminal (tqdm's `disable=None`), so pipes,
logs and `--json` consumers see no control characters.
"""

from __future__ import annotations

import sys
from types import TracebackType

from tqdm import tqdm

_STEPS = 1000  # bar resolution: 0.1 % of the job


class ProgressBar:
    """A `rig.runner.Progress` callback drawing one bar; `write` prints a line on stdout above it."""

    def __init__(self, enabled: bool = True) -> None:
        self._bar = tqdm(
            total=_STEPS,
            file=sys.stderr,
            disable=None if enabled else True,
            leave=False,
            dynamic_ncols=True,
            bar_format="{desc} {percentage:3.0f}%|{bar}| {elapsed}<{remaining}",
        )
        self._label = ""

    def __call__(self, label: str, fraction: float) -> None:
        if label != self._label:
            self._label = label
            self._bar.set_description_str(label, refresh=False)
        done = min(_STEPS, max(0, round(fraction * _STEPS)))
        if done > self._bar.n:  # the job's fraction only grows; a late or repeated report changes nothing
            self._bar.update(done - self._bar.n)

    def write(self, line: str) -> None:
        """Print a line on stdout without tearing the bar (it is cleared and redrawn below the line)."""
        self._bar.write(line, file=sys.stdout)
        sys.stdout.flush()

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
