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

setup(
    packages=sorted(package_dir),
    package_dir=package_dir,
    package_data={"hapticloud.assets": ["**/*"]},
    include_package_data=True,
)
