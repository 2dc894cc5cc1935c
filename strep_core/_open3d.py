"""Import Open3D, preloading the libusb it links against when the system lacks it.

Open3D's Linux wheels need ``libusb-1.0.so.0``, which a bare Debian or a slim container
does not have. The ``libusb-package`` wheel ships that library; loading it globally before
Open3D lets the dynamic linker resolve the dependency by its soname, so a plain
``pip install`` is enough on a fresh machine. Import as ``from strep_core._open3d import o3d``
inside the functions that need it (Open3D takes about a second to import).
"""

from __future__ import annotations

import ctypes
from pathlib import Path


def _preload_libusb() -> bool:
    try:
        import libusb_package
    except ImportError:
        return False
    lib = Path(libusb_package.__file__).parent / "libusb-1.0.so"
    if not lib.exists():
        return False
    ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)
    return True


try:
    import open3d as o3d
except ImportError as exc:  # pragma: no cover - depends on the system's libraries
    if "libusb" not in str(exc) or not _preload_libusb():
        raise
    import open3d as o3d

__all__ = ["o3d"]
