"""Packaging: the wheel carries every shipped asset and finds it through the installed package,
``hapticloud --version`` names the libraries, ``install-desktop`` installs a valid entry and
removes it again (docs/packaging.md)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from importlib.metadata import version
from pathlib import Path

import pytest
from hapticloud.app.commands import install_desktop as desk
from hapticloud.app.commands.version import (
    LIBRARIES,
    NOT_INSTALLED,
    Library,
    library_version,
    version_lines,
)

ROOT = Path(__file__).resolve().parents[2]


def _cli(*args: str, env: dict[str, str] | None = None, cwd: Path = ROOT, timeout: float = 120):
    return subprocess.run(
        [sys.executable, "-m", "hapticloud.app.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        cwd=cwd,
    )


# --version


def test_version_names_hapticloud_and_every_library_with_its_installed_version() -> None:
    out = _cli("--version")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == f"hapticloud {version('hapticloud')}"
    assert lines[1].startswith(f"Python {sys.version.split()[0]} ")
    shown = {line.split("  ")[1].strip(): line.split()[-1] for line in lines[2:]}
    for label, dist in [
        ("Open3D", "open3d"),
        ("numpy", "numpy"),
        ("Pinocchio (pin)", "pin"),
        ("daqp", "daqp"),
        ("quadprog", "quadprog"),
        ("python-can", "python-can"),
        ("PyQt6", "PyQt6"),
        ("Qt", "PyQt6-Qt6"),
        ("VTK", "vtk"),
        ("pyvista", "pyvista"),
    ]:
        assert shown[label] == version(dist), label


def test_a_missing_library_says_not_installed() -> None:
    assert library_version(Library("ghost", "no-such-dist-x", "no_such_module_x")) == NOT_INSTALLED
    lines = version_lines([*LIBRARIES, Library("ghost", "no-such-dist-x", "no_such_module_x")])
    assert lines[-1].split() == ["ghost", "not", "installed"]


def test_without_metadata_the_module_says_its_version() -> None:
    """A bundle may leave a library's metadata out: the imported module still answers."""
    import numpy
    from PyQt6.QtCore import QT_VERSION_STR

    assert library_version(Library("numpy", "no-such-dist-x", "numpy")) == numpy.__version__
    assert library_version(Library("Qt", "PyQt6-Qt6", "PyQt6.QtCore")) == version("PyQt6-Qt6")
    assert QT_VERSION_STR.split(".")[0] == "6"


# install-desktop


def _xdg_env(data_home: Path) -> dict[str, str]:
    return {**os.environ, "XDG_DATA_HOME": str(data_home)}


def test_install_desktop_user_installs_a_valid_entry_icons_and_the_mcap_type(tmp_path) -> None:
    data = tmp_path / "share"
    out = _cli("install-desktop", "--user", env=_xdg_env(data), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    files = desk.DesktopFiles(data)
    for path in files.all():
        assert path.is_file(), path
        assert f"installed {path}" in out.stdout
    entry = files.desktop_entry.read_text()
    assert f"Exec={Path(sys.executable).parent / 'hapticloud'} app %f" in entry
    assert "MimeType=application/vnd.mcap;" in entry
    for size in desk.ICON_SIZES:
        png = files.icon_theme / f"{size}x{size}" / "apps" / "hapticloud.png"
        assert png.read_bytes()[16:24] == size.to_bytes(4, "big") * 2  # the PNG's width, height

    validate = shutil.which("desktop-file-validate")
    assert validate, "desktop-file-utils is missing (packaging/bootstrap.sh installs it)"
    checked = subprocess.run([validate, str(files.desktop_entry)], capture_output=True, text=True)
    assert checked.returncode == 0 and checked.stdout == "", checked.stdout + checked.stderr

    if shutil.which("update-mime-database"):
        assert "application/vnd.mcap:*.mcap" in (data / "mime" / "globs2").read_text()
        assert b"\x89MCAP0\r\n" in (data / "mime" / "magic").read_bytes()
    if shutil.which("update-desktop-database"):
        cache = (data / "applications" / "mimeinfo.cache").read_text()
        assert "application/vnd.mcap=hapticloud.desktop;" in cache

    out = _cli("install-desktop", "--user", "--uninstall", env=_xdg_env(data), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert not [p for p in files.all() if p.exists()]
    if shutil.which("update-mime-database"):
        assert "vnd.mcap" not in (data / "mime" / "globs2").read_text()
    out = _cli("install-desktop", "--user", "--uninstall", env=_xdg_env(data), cwd=tmp_path)
    assert out.returncode == 0 and "nothing to remove" in out.stdout


def test_a_launcher_path_with_spaces_is_quoted_and_still_valid(tmp_path) -> None:
    files = desk.DesktopFiles(tmp_path)
    desk.install(files, ["/opt/my apps/hapticloud"])
    entry = files.desktop_entry.read_text()
    assert 'Exec="/opt/my apps/hapticloud" app %f' in entry
    validate = shutil.which("desktop-file-validate")
    assert validate
    checked = subprocess.run([validate, str(files.desktop_entry)], capture_output=True, text=True)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert desk.exec_quote('a"b$c') == '"a\\\\"b\\\\$c"'
    assert desk.exec_quote("50%") == "50%%"


def test_user_data_home_follows_xdg_and_ignores_a_relative_one(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert desk.data_home(user=True) == tmp_path
    monkeypatch.setenv("XDG_DATA_HOME", "relative/share")
    assert desk.data_home(user=True) == Path.home() / ".local" / "share"
    assert desk.data_home(user=False) == Path("/usr/local/share")


def test_a_system_install_without_permission_says_so_in_one_line(monkeypatch) -> None:
    def refused(*_: object) -> list[Path]:
        raise PermissionError(13, "Permission denied", "/usr/local/share/applications")

    monkeypatch.setattr(desk, "install", refused)
    monkeypatch.setattr(desk, "launcher", lambda: ["/bin/true"])
    with pytest.raises(desk.ConfigError) as err:
        desk.run(desk.argparse.Namespace(user=False, uninstall=False))
    assert str(err.value) == (
        "/usr/local/share/applications: permission denied (run as root, or use --user)"
    )


# the wheel


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stderr[-2000:]
    (path,) = out.glob("hapticloud-*.whl")
    return path


def _tracked_assets() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "assets"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    return [name for name in listed if (ROOT / name).is_file()]


def test_the_wheel_carries_every_tracked_asset_and_nothing_stray(wheel) -> None:
    tracked = _tracked_assets()
    assert {"assets/can/anyexo_drives.dbc", "assets/robot/anyexo.urdf"} <= set(tracked)
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
    in_wheel = {"hapticloud/" + name for name in tracked}
    assert in_wheel <= names, sorted(in_wheel - names)
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
    assert "hapticloud/assets/icons/hapticloud.svg" in names
    for size in desk.ICON_SIZES:
        assert f"hapticloud/assets/icons/hapticloud-{size}.png" in names
    assert "hapticloud/app/commands/install_desktop.py" in names


def test_the_installed_wheel_reads_its_assets_from_itself_not_the_checkout(wheel, tmp_path) -> None:
    """Unpacked into a folder of its own, run from elsewhere: every asset path lies inside it."""
    target = tmp_path / "site"
    with zipfile.ZipFile(wheel) as zf:
        zf.extractall(target)
    code = (
        "import sys\n"
        "from hapticloud.core.scene import scenes_dir, resolve_scene\n"
        "from hapticloud.core.robot import default_urdf_path, RobotModel\n"
        "from hapticloud.hardware.drives.codec import default_dbc_path\n"
        "from hapticloud.assets import asset_path\n"
        "RobotModel.load()\n"
        "for p in (scenes_dir(), resolve_scene('impacts'), default_urdf_path(),\n"
        "          default_dbc_path(), asset_path('icons', 'hapticloud.svg')):\n"
        "    assert p.exists(), p\n"
        "    print(p)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(target)}
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=elsewhere
    )
    assert out.returncode == 0, out.stderr
    paths = out.stdout.split()
    assert len(paths) == 5
    for path in paths:
        assert Path(path).is_relative_to(target), path
