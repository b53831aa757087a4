"""Maps the fixed layout onto installed names.

The design card puts ``core/``, ``hardware/``, ``app/`` and ``assets/`` at the repository root;
they install as ``hapticloud.core``, ``hapticloud.hardware``, ``hapticloud.app`` and
``hapticloud.assets``. ``hapticloud`` itself is an implicit namespace package. Every sub-package
is listed with its own folder so that editable installs resolve them too.
"""

from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).parent
package_dir: dict[str, str] = {}
for top in ("core", "hardware", "app"):
    package_dir[f"hapticloud.{top}"] = top
    for sub in find_packages(str(ROOT / top)):
        package_dir[f"hapticloud.{top}.{sub}"] = f"{top}/" + sub.replace(".", "/")
package_dir["hapticloud.assets"] = "assets"

# What the program reads at run time (hapticloud.assets.asset_path); named by kind so that a
# stray file in assets/ (a __pycache__, an editor's backup) stays out of the wheel.
ASSET_FILES = [
    "scenes/*.toml",
    "robot/*.urdf",
    "robot/*.md",
    "can/*.dbc",
    "presets/*.toml",
    "icons/*.svg",
    "icons/*.png",
]

setup(
    packages=sorted(package_dir),
    package_dir=package_dir,
    package_data={"hapticloud.assets": ASSET_FILES},
    include_package_data=False,
)
