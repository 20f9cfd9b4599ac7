"""Replace byte-identical copies of shared libraries by symlinks (build time only).

Wheels cannot carry symlinks, so the ROS wheels ship libfastrtps.so, libfastrtps.so.2.14
and libfastrtps.so.2.14.5 as three full copies, and each ros_*.libs folder (auditwheel)
vendors its own copy of the same tinyxml2, lttng-ust, urcu ... libraries. Each copy keeps
its file name (what the loader looks for) and becomes a relative link to one real file.

Usage: python dedupe_libs.py DIR [DIR ...]
"""
import hashlib
import os
import sys
from pathlib import Path


def main(folders: list[Path]) -> None:
    groups: dict[tuple[int, str], list[Path]] = {}
    for folder in folders:
        for path in sorted(folder.glob("*.so*")):
            if path.is_file() and not path.is_symlink():
                digest = hashlib.sha256(path.read_bytes()).hexdigest()
                groups.setdefault((path.stat().st_size, digest), []).append(path)
    saved = 0
    for (size, _), paths in groups.items():
        if len(paths) < 2:
            continue
        keep = max(paths, key=lambda p: (len(p.name), -len(str(p))))  # the fully versioned name
        for path in paths:
            if path != keep:
                path.unlink()
                os.symlink(os.path.relpath(keep, path.parent), path)
                saved += size
    print(f"dedupe_libs: {saved / 1e6:.1f} MB of duplicate libraries replaced by symlinks")


if __name__ == "__main__":
    main([Path(arg) for arg in sys.argv[1:]])
