"""Reading the PNG captures given on the command line, with one-line errors naming the file.

Images are 8-bit grayscale or BGR PNGs, one per camera exposure (SPEC §6). A missing, empty,
non-image, 16-bit or odd-shaped file raises :class:`~omnid.errors.InputError` naming it, and
so does a capture whose four files differ in size or do not fit the calibration.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from omnid.core.types import StereoCapture
from omnid.errors import InputError


def read_image(path: str | Path) -> NDArray[np.uint8]:
    """An 8-bit gray (H, W) or BGR (H, W, 3) image from ``path``; alpha is dropped."""
    import cv2

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such image file")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from exc
    if not data:
        raise InputError(f"{p}: empty file, not an image")
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(f"{p}: not a readable image (expected an 8-bit PNG)")
    if img.dtype != np.uint8:
        raise InputError(f"{p}: {img.dtype} pixels, expected an 8-bit image")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise InputError(f"{p}: unsupported image layout {img.shape}")
    return np.ascontiguousarray(img)


def read_capture(
    mask1: str | Path,
    base1: str | Path,
    mask2: str | Path,
    base2: str | Path,
    expected_shape: tuple[int, int] | None = None,
) -> StereoCapture:
    """The four images of a stereo capture; all must have one size (and ``expected_shape``)."""
    paths = [Path(mask1), Path(base1), Path(mask2), Path(base2)]
    images = [read_image(p) for p in paths]
    first = images[0].shape[:2]
    ref = expected_shape if expected_shape is not None else first
    what = "the calibration's image size" if expected_shape is not None else f"{paths[0]}"
    for p, img in zip(paths, images, strict=True):
        if img.shape[:2] != tuple(ref):
            raise InputError(
                f"{p}: image is {img.shape[1]}x{img.shape[0]} px, but {what} is "
                f"{ref[1]}x{ref[0]} px"
            )
    gray = any(img.ndim == 2 for img in images)
    if gray:  # mixed gray/BGR: compare like with like (the laser is green)
        images = [img if img.ndim == 2 else np.ascontiguousarray(img[:, :, 1]) for img in images]
    return StereoCapture(images[0], images[1], images[2], images[3])


def current_umask() -> int:
    """The process's file-creation mask (read from /proc, so it is not changed even briefly;
    elsewhere the classic set-and-restore)."""
    import os

    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | Path, data: bytes, fsync: bool = False) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file beside it, then a rename, so a
    reader never sees half a file and a failed write leaves the old file alone. The file gets
    the permissions a plain ``open(path, "w")`` would (0666 less the umask), not the temporary
    file's 0600. ``fsync``: on disk before the rename. An unwritable place raises
    :class:`InputError` naming ``path``, never the temporary file."""
    write_files_atomic([(path, data)], fsync)


def png_bytes(path: str | Path, image: NDArray[np.uint8]) -> bytes:
    """An 8-bit gray or BGR image encoded as PNG, to be written to ``path`` (named in the
    error)."""
    import cv2

    ok, buf = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - cv2 fails only on unusable arrays
        raise InputError(f"{path}: PNG encoding failed")
    return bytes(buf.tobytes())


def write_png(path: str | Path, image: NDArray[np.uint8]) -> None:
    """Encode an 8-bit gray or BGR image as PNG and write it atomically (see
    :func:`write_bytes_atomic`)."""
    write_bytes_atomic(path, png_bytes(path, image))


def refuse_clobbering(outputs: dict[str, str | None], inputs: dict[str, str]) -> None:
    """Raise :class:`InputError` when an output path (option name → path) is one of the inputs
    or another output: writing it would destroy a capture or the calibration the command just
    read (``--out floor_mask1.png``), or one output would silently replace the other."""
    import os

    def same(a: str, b: str) -> bool:
        try:
            return os.path.samefile(a, b)
        except OSError:  # one of them does not exist (yet): compare the names
            return os.path.abspath(a) == os.path.abspath(b)

    seen: dict[str, str] = dict(inputs)
    for option, path in outputs.items():
        if not path:
            continue
        for other, other_path in seen.items():
            if same(path, other_path):
                raise InputError(
                    f"{option} {path} is also {other}: writing it would replace that file; "
                    "give the output a path of its own"
                )
        seen[option] = path


def write_files_atomic(files: Sequence[tuple[str | Path, bytes]], fsync: bool = False) -> None:
    """Write several files all or none: every temporary file is made and filled first (an
    unwritable place fails before any file is touched), then all are renamed into place. An
    error raises :class:`InputError` naming the path, never a temporary file. The files get
    the permissions a plain ``open(path, "w")`` would; ``fsync``: on disk before the renames."""
    import os
    import tempfile

    for path, _ in files:  # the one rename that fails on a writable place: onto a folder
        if Path(path).is_dir():
            raise InputError(f"{path}: cannot write (Is a directory)")
    temps: list[tuple[str, Path]] = []
    try:
        for path, data in files:
            p = Path(path)
            try:
                fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent or ".")
            except OSError as exc:
                raise InputError(f"{p}: cannot write ({exc.strerror or exc})") from None
            temps.append((tmp, p))
            try:
                os.fchmod(fd, 0o666 & ~current_umask())
                with os.fdopen(fd, "wb") as f:
                    f.write(data)
                    if fsync:
                        f.flush()
                        os.fsync(f.fileno())
            except OSError as exc:
                raise InputError(f"{p}: cannot write ({exc.strerror or exc})") from None
        for tmp, p in temps:
            try:
                os.replace(tmp, p)
            except OSError as exc:
                raise InputError(f"{p}: cannot write ({exc.strerror or exc})") from None
    finally:
        for tmp, _ in temps:
            Path(tmp).unlink(missing_ok=True)
