"""``hapticloud install-desktop [--user] [--uninstall]``: the desktop menu entry, icons and the
MIME type of recordings, after the freedesktop conventions.

Installed under the XDG data folder (``--user``: ``$XDG_DATA_HOME``, by default
``~/.local/share``; otherwise ``/usr/local/share``, the system folder for software installed by
hand):

- ``applications/hapticloud.desktop``: starts ``hapticloud app`` (the demo scene), or opens the
  recording it is given (``%f``);
- ``icons/hicolor/scalable/apps/hapticloud.svg`` and ``icons/hicolor/NxN/apps/hapticloud.png``;
- ``mime/packages/hapticloud.xml``: ``application/vnd.mcap`` (the registered MCAP type), known
  by its ``*.mcap`` name and by its magic bytes.

Then the caches are refreshed with ``update-desktop-database``, ``update-mime-database`` and
``gtk-update-icon-cache`` where they exist (a desktop without them rescans by itself).
``--uninstall`` removes exactly these files and refreshes the caches again.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from hapticloud.assets import asset_path
from hapticloud.core.errors import ConfigError

APP_ID = "hapticloud"
MIME_TYPE = "application/vnd.mcap"
ICON_SIZES = (16, 22, 24, 32, 48, 64, 128, 256)
SYSTEM_DATA_HOME = Path("/usr/local/share")

MIME_XML = f"""<?xml version="1.0" encoding="UTF-8"?>
<mime-info xmlns="http://www.freedesktop.org/standards/shared-mime-info">
  <mime-type type="{MIME_TYPE}">
    <comment>MCAP recording</comment>
    <acronym>MCAP</acronym>
    <expanded-acronym>Modular Container for Asynchronous Pub/Sub messages</expanded-acronym>
    <icon name="{APP_ID}"/>
    <glob pattern="*.mcap"/>
    <magic priority="50">
      <match type="string" offset="0" value="\\x89MCAP0\\r\\n"/>
    </magic>
  </mime-type>
</mime-info>
"""


@dataclass(frozen=True)
class DesktopFiles:
    """Where each installed file goes under one XDG data folder."""

    data_home: Path

    @property
    def desktop_entry(self) -> Path:
        return self.data_home / "applications" / f"{APP_ID}.desktop"

    @property
    def mime_package(self) -> Path:
        return self.data_home / "mime" / "packages" / f"{APP_ID}.xml"

    @property
    def icon_theme(self) -> Path:
        return self.data_home / "icons" / "hicolor"

    def icons(self) -> dict[Path, Path]:
        """Installed icon path -> the shipped file it is copied from."""
        out = {
            self.icon_theme / "scalable" / "apps" / f"{APP_ID}.svg": asset_path(
                "icons", f"{APP_ID}.svg"
            )
        }
        for size in ICON_SIZES:
            target = self.icon_theme / f"{size}x{size}" / "apps" / f"{APP_ID}.png"
            out[target] = asset_path("icons", f"{APP_ID}-{size}.png")
        return out

    def all(self) -> list[Path]:
        return [self.desktop_entry, self.mime_package, *self.icons()]


def data_home(user: bool) -> Path:
    """The XDG data folder to install into (see the module's docstring)."""
    if not user:
        return SYSTEM_DATA_HOME
    xdg = os.environ.get("XDG_DATA_HOME", "")
    # The spec: a relative XDG_DATA_HOME is invalid and is ignored.
    if xdg and Path(xdg).is_absolute():
        return Path(xdg)
    return Path.home() / ".local" / "share"


def launcher() -> list[str]:
    """The command that starts this hapticloud: the bundle's executable, or the console script
    beside this Python (a virtual environment need not be on PATH)."""
    if getattr(sys, "frozen", False):
        return [str(Path(sys.executable).resolve())]
    script = Path(sys.executable).parent / "hapticloud"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    found = shutil.which("hapticloud")
    if found:
        return [str(Path(found).resolve())]
    raise ConfigError(
        f"no 'hapticloud' executable beside {sys.executable} or on PATH: install the package "
        "(pip install hapticloud-*.whl) before its desktop entry"
    )


def exec_quote(arg: str) -> str:
    """One argument of a desktop entry's Exec key, quoted as the spec asks where needed."""
    reserved = set(" \t\n\"'\\><~|&;$*?#()`")
    if not arg or any(c in reserved for c in arg):
        escaped = "".join("\\" + c if c in '"`$\\' else c for c in arg)
        arg = f'"{escaped}"'
    # In a desktop file's string value a backslash itself is escaped once more, and a literal
    # % (not a field code) is written %%.
    return arg.replace("\\", "\\\\").replace("%", "%%")


def desktop_entry(command: list[str]) -> str:
    """The ``.desktop`` file's text for ``command`` (the executable and its first arguments)."""
    exe = " ".join(exec_quote(part) for part in command)
    return "\n".join(
        [
            "[Desktop Entry]",
            "Type=Application",
            "Version=1.4",
            "Name=hapticloud",
            "GenericName=Haptic rendering on point clouds",
            "Comment=Live point clouds, haptic surfaces and sessions of the rehabilitation "
            "exoskeleton; opens MCAP recordings",
            f"Icon={APP_ID}",
            f"TryExec={command[0]}",
            f"Exec={exe} app %f",
            "Terminal=false",
            "StartupNotify=true",
            f"MimeType={MIME_TYPE};",
            "Categories=Science;Robotics;MedicalSoftware;",
            "Keywords=haptics;exoskeleton;rehabilitation;point cloud;robot;mcap;",
            "",
        ]
    )


def install(files: DesktopFiles, command: list[str]) -> list[Path]:
    """Writes every file of ``files`` (the entry starts ``command``); returns them."""
    for target, source in files.icons().items():
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
    files.mime_package.parent.mkdir(parents=True, exist_ok=True)
    files.mime_package.write_text(MIME_XML, encoding="utf-8")
    files.desktop_entry.parent.mkdir(parents=True, exist_ok=True)
    files.desktop_entry.write_text(desktop_entry(command), encoding="utf-8")
    return files.all()


def uninstall(files: DesktopFiles) -> list[Path]:
    """Removes the files :func:`install` writes (those that exist); returns the removed ones."""
    removed = []
    for path in files.all():
        if path.is_file():
            path.unlink()
            removed.append(path)
    return removed


def refresh_caches(files: DesktopFiles) -> list[str]:
    """Runs the freedesktop cache tools that exist; returns one line per tool that ran."""
    steps = [
        ("update-desktop-database", ["-q", str(files.desktop_entry.parent)]),
        ("update-mime-database", [str(files.mime_package.parent.parent)]),
        ("gtk-update-icon-cache", ["-q", "-f", "-t", str(files.icon_theme)]),
    ]
    done = []
    for tool, args in steps:
        exe = shutil.which(tool)
        if exe is None:
            continue
        result = subprocess.run([exe, *args], capture_output=True, text=True, check=False)
        status = "ok" if result.returncode == 0 else f"exit {result.returncode}: "
        detail = "" if result.returncode == 0 else (result.stderr.strip().splitlines() or [""])[-1]
        done.append(f"{tool} {status}{detail}")
    return done


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "install-desktop",
        help="add hapticloud to the desktop menu (entry, icons, the .mcap file type)",
        description="Installs a desktop entry that starts the app or opens a recording "
        "(FILE.mcap), the icons and the MIME type application/vnd.mcap, after the freedesktop "
        "conventions, then refreshes the desktop, MIME and icon caches where their tools exist. "
        "System-wide under /usr/local/share by default (needs root); --user installs under "
        "$XDG_DATA_HOME (~/.local/share).",
    )
    parser.add_argument(
        "--user", action="store_true", help="for the current user only ($XDG_DATA_HOME)"
    )
    parser.add_argument(
        "--uninstall", action="store_true", help="remove what install-desktop installed"
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    files = DesktopFiles(data_home(args.user))
    try:
        if args.uninstall:
            changed = uninstall(files)
            verb = "removed"
        else:
            changed = install(files, launcher())
            verb = "installed"
    except PermissionError as err:
        hint = "" if args.user else " (run as root, or use --user)"
        raise ConfigError(f"{err.filename}: permission denied{hint}") from None
    for path in changed:
        print(f"{verb} {path}")
    if not changed:
        print(f"nothing to remove under {files.data_home}")
    for line in refresh_caches(files):
        print(line)
    return 0
