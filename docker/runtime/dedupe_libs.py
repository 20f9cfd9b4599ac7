"""Replace byte-identical copies of a shared library by symlinks (build time only).

Wheels cannot carry symlinks, so the ROS wheels ship libfastrtps.so, libfastrtps.so.2.14
and libfastrtps.so.2.14.5 as three full copies. Usage: python dedupe_libs.py DIR
"""
import hashlib
import os
import sys
from pathlib import Path


def main(folder: Path) -> None:
    groups: dict[tuple[int, str], list[Path]] = {}
    for path in folder.glob("*.so*"):
        if path.is_file() and not path.is_symlink():
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            groups.setdefault((path.stat().st_size, digest), []).append(path)
    saved = 0
    for (size, _), paths in groups.items():
        if len(paths) < 2:
            continue
        keep = max(paths, key=lambda p: len(p.name))  # the fully versioned name
        for path in paths:
            if path != keep:
                path.unlink()
                os.symlink(keep.name, path)
                saved += size
    print(f"dedupe_libs: {saved / 1e6:.1f} MB of duplicate libraries replaced by symlinks")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
