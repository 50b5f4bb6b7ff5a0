"""hdrig installs as a wheel and works from any folder (issue 24): the presets, rig files and EDS (the
`configs` package), the service's page (`api/static`) and the catalog's migrations are package data, read
through `importlib.resources`, never from the source tree.

The wheel is built from a copy of the checkout and installed without its dependencies into a new virtual
environment whose only link to this one is a .pth naming this environment's site-packages (the installed
dependencies; not the checkout, whose editable-install hook lives in a .pth that is not read from there).
Every command runs from a folder outside the checkout.
"""

from __future__ import annotations

import importlib.metadata
import os
import shutil
import socket
import sqlite3
import subprocess
import sys
import sysconfig
import time
import urllib.request
import zipfile
from pathlib import Path

import pytest

from rig.store.catalog import CATALOG_FILE, head_revision

ROOT = Path(__file__).resolve().parents[1]
# A checkout's generated and private folders: the build's copy of the sources leaves them out.
NOT_SOURCES = shutil.ignore_patterns(
    ".venv", ".git", "build", "dist", "*.egg-info", "__pycache__", ".*_cache", "results", "out", ".hdrig"
)
SERVE_START_S = 120.0  # under a loaded CI machine the service's first start imports and compiles


def _pip(python: str | Path, command: str) -> list[str]:
    """`python`'s pip, offline and for hdrig alone: its dependencies are this environment's."""
    return [str(python), "-m", "pip", command, "--quiet", "--no-deps", "--no-index"]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The checkout's wheel, built from a copy (a build writes build/ and *.egg-info beside the sources)."""
    backend = importlib.metadata.version("setuptools")
    assert tuple(int(p) for p in backend.split(".")[:2]) >= (70, 1), (
        f"setuptools {backend}: the dev extra's setuptools>=70.1 builds the wheel (make install)"
    )
    work = tmp_path_factory.mktemp("wheel")
    sources = work / "src"
    shutil.copytree(ROOT, sources, ignore=NOT_SOURCES)
    # No build isolation: the dev extra installs the build backend, so the test needs no index.
    subprocess.run(
        [*_pip(sys.executable, "wheel"), "--no-build-isolation", "-w", str(work / "dist"), str(sources)],
        check=True,
        cwd=work,
    )
    (built,) = (work / "dist").glob("hdrig-*.whl")
    return built


@pytest.fixture(scope="module")
def venv(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A new environment holding the wheel, borrowing this environment's installed dependencies."""
    target = tmp_path_factory.mktemp("venv") / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(target)], check=True)
    site = Path(
        sysconfig.get_path("purelib", vars={"base": str(target), "platbase": str(target)}),
    )
    borrowed = {sysconfig.get_path("purelib"), sysconfig.get_path("platlib")}
    assert not any(Path(p).resolve() == ROOT for p in borrowed)
    (site / "borrowed-dependencies.pth").write_text("".join(f"{p}\n" for p in sorted(borrowed)))
    # --ignore-installed: pip sees this environment's editable hdrig through the .pth; it must neither
    # count it as installed nor touch it.
    subprocess.run(
        [*_pip(target / "bin" / "python", "install"), "--ignore-installed", str(wheel)],
        check=True,
        cwd=target.parent,
    )
    return target


def _env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "HDRIG_CATALOG")}
    return env | {"HDRIG_HOME": str(home)}


def _run(venv: Path, cwd: Path, *args: str, timeout_s: float = 600.0) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        [str(venv / "bin" / args[0]), *args[1:]],
        cwd=cwd,
        env=_env(cwd / "home"),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    assert done.returncode == 0, f"{' '.join(args)}: exit {done.returncode}\n{done.stdout}\n{done.stderr}"
    return done


def test_wheel_holds_the_data_files(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    for kind in ("models", "rigs", "eds"):
        in_tree = {f"configs/{kind}/{p.name}" for p in (ROOT / "configs" / kind).iterdir() if p.is_file()}
        assert in_tree and in_tree <= names, in_tree - names
    assert "configs/__init__.py" in names
    page = ROOT / "api" / "static"
    static = {f"api/static/{p.relative_to(page).as_posix()}" for p in page.rglob("*") if p.is_file()}
    assert "api/static/index.html" in static and static <= names, static - names
    migrations = {p.name for p in (ROOT / "rig/store/catalog_migrations/versions").glob("r*.py")}
    assert migrations and {f"rig/store/catalog_migrations/versions/{m}" for m in migrations} <= names
    assert "rig/store/catalog_migrations/env.py" in names


def test_installed_package_is_the_wheel_not_the_checkout(venv: Path, tmp_path: Path) -> None:
    where = "import configs, model, rig; print(model.__file__, configs.__file__, rig.__file__)"
    done = _run(venv, tmp_path, "python", "-c", where)
    for where in done.stdout.split():
        assert Path(where).resolve().is_relative_to(venv.resolve()), done.stdout


def test_model_show_and_a_campaign_from_another_folder(venv: Path, tmp_path: Path) -> None:
    shown = _run(venv, tmp_path, "hdrig", "model", "show", "seed")
    assert shown.stdout.startswith("seed: ")
    ran = _run(venv, tmp_path, "hdrig", "run", "campaign", "--rig", "sim")
    lines = [line for line in ran.stdout.splitlines() if "  complete  " in line]
    assert len(lines) >= 5, ran.stdout
    # The store's catalog was made by the wheel's migrations, up to the newest.
    catalog = sqlite3.connect(f"file:{tmp_path / 'home' / CATALOG_FILE}?mode=ro", uri=True)
    try:
        (version,) = catalog.execute("SELECT version_num FROM alembic_version").fetchone()
    finally:
        catalog.close()
    assert version == head_revision()


def test_serve_serves_its_page(venv: Path, tmp_path: Path) -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    service = subprocess.Popen(
        [str(venv / "bin" / "hdrig"), "serve", "--rig", "sim", "--host", "127.0.0.1", "--port", str(port)],
        cwd=tmp_path,
        env=_env(tmp_path / "home"),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        page = _get_when_up(f"http://127.0.0.1:{port}/", service)
        assert "<html" in page.lower()
        script = urllib.request.urlopen(f"http://127.0.0.1:{port}/static/app.js", timeout=30).read()
        assert script
    finally:
        service.terminate()
        out, _ = service.communicate(timeout=60)
    assert service.returncode is not None, out


def _get_when_up(url: str, service: subprocess.Popen[str]) -> str:
    deadline = time.monotonic() + SERVE_START_S
    while True:
        if service.poll() is not None:
            said = service.stdout.read() if service.stdout else ""
            raise AssertionError(f"hdrig serve exited {service.returncode}: {said}")
        try:
            with urllib.request.urlopen(url, timeout=10) as answer:
                return str(answer.read().decode())
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)
