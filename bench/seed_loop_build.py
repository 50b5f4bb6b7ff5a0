"""Compiles bench/seed_loop.c, the plain C loop the simulator is measured against, with the kernel's
vector layouts from the registry (`model.registry.slot_defines`), so the two never disagree on a slot."""

from __future__ import annotations

import subprocess
from pathlib import Path

from model.registry import slot_defines

SOURCE = Path(__file__).resolve().parent / "seed_loop.c"


def compile_seed_loop(work: Path) -> Path:
    """The loop's executable, built in `work` (gcc -O2 -march=native)."""
    loop = work / "seed_loop"
    subprocess.run(
        ["gcc", "-O2", "-march=native", *slot_defines(), "-o", str(loop), str(SOURCE), "-lm"], check=True
    )
    return loop
