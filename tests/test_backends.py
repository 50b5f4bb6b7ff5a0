"""Backends are found by name: the built-in table, a lab's own through the `hdrig.backends` entry points,
and an unknown name is a one-line error naming the known ones.

The lab's backend is a real installed distribution as `importlib.metadata` sees one: a `*.dist-info`
folder with `entry_points.txt` and the module it names, both on `sys.path`.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from rig.config import RIG_DIR, RigConfig, load_rig_config
from rig.interface import BUILTIN_BACKENDS, RigError, backend_names, open_rig

LAB_BACKEND = "lab-bench"
BACKEND_PACKAGES = ("sim_backend", "drivers", "can", "canopen", "serial")
LAB_MODULE = textwrap.dedent(
    '''
    """A lab's own bench, outside hdrig."""

    from rig.interface import Rig


    class LabBenchRig(Rig):
        gear_ratio = 0.01
        torque_constant_nm_per_a = 0.1

        def _run_cycles(self, mode, setpoint, tau_ext):
            raise NotImplementedError

        def _enable(self):
            return None

        def _disable(self):
            return None

        def _quick_stop(self):
            return None
    '''
)


def sim_config(backend: str) -> RigConfig:
    return load_rig_config(RIG_DIR / "sim.yaml").model_copy(update={"backend": backend})


@pytest.fixture
def lab_distribution(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """Install `lab_bench` (a module and its dist-info declaring `lab-bench`) on sys.path; its module name."""
    (tmp_path / "lab_bench.py").write_text(LAB_MODULE)
    dist_info = tmp_path / "lab_bench-1.0.dist-info"
    dist_info.mkdir()
    (dist_info / "METADATA").write_text("Metadata-Version: 2.1\nName: lab-bench\nVersion: 1.0\n")
    (dist_info / "entry_points.txt").write_text(f"[hdrig.backends]\n{LAB_BACKEND} = lab_bench:LabBenchRig\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "lab_bench"
    sys.modules.pop("lab_bench", None)


def test_a_backend_installed_as_an_entry_point_is_opened_by_its_name(lab_distribution: str) -> None:
    assert LAB_BACKEND in backend_names()
    with open_rig(sim_config(LAB_BACKEND)) as rig:
        assert type(rig).__module__ == lab_distribution
        assert type(rig).__name__ == "LabBenchRig"
        assert rig.config.backend == LAB_BACKEND


def test_an_unknown_backend_is_one_line_naming_the_known_ones(lab_distribution: str) -> None:
    with pytest.raises(RigError) as info:
        open_rig(sim_config("no-such-bench"))
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("rig 'sim': unknown backend 'no-such-bench' (backends: ")
    for name in [*BUILTIN_BACKENDS, LAB_BACKEND]:
        assert name in message


def test_opening_the_sim_backend_loads_no_other_backend() -> None:
    # A fresh interpreter: what this process imported already would hide what open_rig imports.
    code = textwrap.dedent(
        f"""
        import sys
        from rig.config import load_rig_config
        from rig.interface import open_rig
        def backends():
            return sorted(m for m in sys.modules if m.split(".")[0] in {BACKEND_PACKAGES!r})
        assert not backends()
        open_rig(load_rig_config({str(RIG_DIR / "sim.yaml")!r})).close()
        print(backends())
        """
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "['sim_backend', 'sim_backend.inprocess', 'sim_backend.simulated_drive']"
