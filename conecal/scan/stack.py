"""Lazy projection stacks: a multi-page TIFF or a folder of single-page TIFFs.

Frames are read one at a time and converted to attenuation ``-ln(I/I0)``;
memory stays bounded by the frames in flight, never the whole stack.
Uncompressed contiguous pages are memory-mapped; other pages are read
through a file handle per thread and per process, so that frames can be
read in parallel by threads or forked workers.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import tifffile

from ..errors import InputError

# Transmission is floored here before the log: a zero count is real data
# (a dead pixel, a fully opaque spot), not a reason to fail.
_T_FLOOR = 1e-6


# A flat whose gain is zero over more than this share of the detector is a
# wrong file, not an intensifier's dark surround.
_DEAD_SHARE = 0.5
# a pixel whose flat is brighter than the dark by less than this share of the
# open field's (the flat's 90th percentile) sees almost no beam
_DIM_SHARE = 0.25


def grey(page, img: np.ndarray) -> np.ndarray:
    """A page stored with several samples per pixel (an image viewer's RGB
    export of a grey radiograph; a stack written as one planar page) read as
    the mean of its samples, alpha channels left out. Other pages as read."""
    n = int(getattr(page, "samplesperpixel", 1) or 1)
    if n <= 1 or img.ndim != 3:
        return img
    axis = 0 if int(getattr(page, "planarconfig", 1)) == 2 else -1
    extra = tuple(getattr(page, "extrasamples", ()) or ())
    # TIFF ExtraSamples 1 and 2: associated and unassociated alpha
    alpha = {n - len(extra) + i for i, e in enumerate(extra) if int(e) in (1, 2)}
    keep = [i for i in range(img.shape[axis]) if i not in alpha] or [0]
    samples = np.take(img, keep, axis=axis)
    first = np.take(samples, [0], axis=axis)
    if (samples == first).all():     # grey stored as colour: as stored, its dtype kept
        return np.squeeze(first, axis=axis)
    return samples.astype(np.float64).mean(axis=axis)


def _read_mean_image(path: Path, shape) -> np.ndarray:
    try:
        with tifffile.TiffFile(path) as tf:
            acc = None
            for k, page in enumerate(tf.pages):
                img = grey(page, page.asarray()).astype(np.float64)
                if img.shape != tuple(shape):
                    raise InputError(f"{path}: page {k}: shape {img.shape}, expected {tuple(shape)} (rows, cols)")
                acc = img if acc is None else acc + img
            if acc is None:
                raise InputError(f"{path}: no image pages")
            return (acc / len(tf.pages)).astype(np.float32)
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except InputError:
        raise
    except Exception as exc:  # tifffile raises many kinds for damaged files
        raise InputError(f"{path}: unreadable TIFF ({type(exc).__name__}: {exc})") from None


class ProjectionStack:
    """Read-only access to frame ``k`` of a scan, as float32 attenuation.

    Parameters
    ----------
    path : a multi-page TIFF, or a folder of TIFFs (sorted by name).
    shape : (rows, cols) every frame must have.
    values : 'attenuation', 'transmission' or 'raw'.
    flat, dark : paths for 'raw' (multi-page stacks are averaged).
    """

    def __init__(self, path, shape, values="attenuation", flat=None, dark=None):
        self.path = Path(path)
        self.shape = tuple(int(s) for s in shape)
        self.values = values
        self._local = threading.local()
        if self.path.is_dir():
            self._files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in (".tif", ".tiff"))
            if not self._files:
                raise InputError(f"{self.path}: folder holds no .tif files")
            self._n = len(self._files)
        elif self.path.is_file():
            self._files = None
            self._views = None
            try:
                with tifffile.TiffFile(self.path) as tf:
                    self._n = len(tf.pages)
                    self._views = self._contiguous_layout(tf)
            except Exception as exc:
                raise InputError(f"{self.path}: unreadable TIFF ({type(exc).__name__}: {exc})") from None
            if self._n == 0:
                raise InputError(f"{self.path}: no image pages")
        else:
            raise InputError(f"{self.path}: file not found")
        self._flat = self._dark = None
        self.dead_pixels = 0   # flat not brighter than dark (raw values)
        self.field_mask = None  # pixels that see the beam (raw values; None: not known)
        if values == "raw":
            self._dark = _read_mean_image(Path(dark), self.shape)
            flat_img = _read_mean_image(Path(flat), self.shape)
            gain = flat_img - self._dark
            dead = gain <= 0
            if dead.mean() > _DEAD_SHARE:
                k = np.flatnonzero(dead.reshape(-1))[0]
                r, c = divmod(int(k), self.shape[1])
                raise InputError(f"{flat}: {dead.mean():.0%} of the pixels, the first at (row {r}, col {c}), are "
                                 f"not brighter than the dark image")
            # An intensifier's flat is black outside its circular field: those
            # pixels never see the beam and read as no transmission, as detect
            # takes the dark surround of a frame (the pixels' count is kept for
            # the user to be told).
            # (so do the pixels of its rim and the glare beyond it, where the
            # flat is well above the dark but far below the field: 50 of 900
            # grey levels in an independent renderer's 10-bit export, 40 of 222
            # on its 8-bit log display; divided by it, their noise became
            # speckle read as 130 touching shadows, whose joint fit took 20 GB
            # to hold; in the field an intensifier's vignetting leaves >= 40 %)
            dead |= gain < _DIM_SHARE * np.percentile(gain[~dead], 90)
            gain[dead] = np.inf
            self.dead_pixels = int(dead.sum())
            self.field_mask = ~dead
            self._flat = gain

    def __len__(self) -> int:
        return self._n

    def _contiguous_layout(self, tf):
        """(offset, dtype) per page when every page is stored uncompressed and
        contiguous with the expected shape: such frames are read with one
        positioned read each (no TIFF parsing per frame). Not a memory map:
        every page of a mapped stack that was read counts in the process's
        resident memory until the kernel drops it, so a pass over a 6 GB
        stack would look like 6 GB used. None otherwise."""
        size = Path(self.path).stat().st_size
        layout = []
        for page in tf.pages:
            offsets, counts = page.dataoffsets, page.databytecounts
            if (page.compression != 1 or tuple(page.shape) != self.shape or page.dtype is None
                    or getattr(page, "samplesperpixel", 1) != 1 or not offsets
                    or any(o + c != o2 for o, c, o2 in zip(offsets, counts, offsets[1:]))):
                return None
            offset, nbytes = offsets[0], sum(counts)
            dtype = np.dtype(page.dtype).newbyteorder(tf.byteorder)
            if nbytes != dtype.itemsize * self.shape[0] * self.shape[1] or offset + nbytes > size:
                return None
            layout.append((int(offset), dtype))
        return layout or None

    def _fd(self) -> int:
        # one descriptor per process: os.pread has no shared file offset, but a
        # forked worker must not close its parent's descriptor
        held = getattr(self._local, "fd", None)
        if held is None or held[0] != os.getpid():
            held = (os.getpid(), os.open(self.path, os.O_RDONLY))
            self._local.fd = held
        return held[1]

    def _handle(self) -> tifffile.TiffFile:
        # one handle per thread and per process: a forked worker must not
        # share its parent's file offset
        held = getattr(self._local, "tf", None)
        if held is None or held[0] != os.getpid():
            held = (os.getpid(), tifffile.TiffFile(self.path))
            self._local.tf = held
        return held[1]

    def read_raw(self, k: int) -> np.ndarray:
        """Frame ``k`` as stored (no conversion; a colour page as ``grey``)."""
        if not 0 <= k < self._n:
            raise IndexError(f"frame {k} out of range 0..{self._n - 1}")
        where = self._files[k] if self._files is not None else self.path
        if self._files is None and self._views is not None:
            offset, dtype = self._views[k]
            n = dtype.itemsize * self.shape[0] * self.shape[1]
            buf = os.pread(self._fd(), n, offset)
            if len(buf) != n:
                raise InputError(f"{where}: frame {k}: truncated ({len(buf)} of {n} bytes)")
            return np.frombuffer(buf, dtype).reshape(self.shape)
        try:
            if self._files is not None:
                with tifffile.TiffFile(self._files[k]) as tf:
                    img = grey(tf.pages[0], tf.pages[0].asarray())
            else:
                page = self._handle().pages[k]
                img = grey(page, page.asarray())
        except Exception as exc:
            raise InputError(f"{where}: frame {k}: truncated or unreadable ({type(exc).__name__}: {exc})") from None
        if img.shape != self.shape:
            raise InputError(f"{where}: frame {k}: shape {img.shape}, scan.yaml says {self.shape} (rows, cols)")
        return img

    def check_finite(self, k: int, a: np.ndarray) -> None:
        """Raise InputError naming frame ``k`` and the first non-finite pixel of ``a``."""
        if not np.isfinite(a).all():
            bad = np.flatnonzero(~np.isfinite(a.reshape(-1)))[0]
            r, c = divmod(int(bad), self.shape[1])
            where = self._files[k] if self._files is not None else self.path
            raise InputError(f"{where}: frame {k}: pixel (row {r}, col {c}) is {a[r, c]}")

    def read(self, k: int, check: bool = True) -> np.ndarray:
        """Frame ``k`` as float32 attenuation (read-only when read as stored).

        Raises on NaN/inf pixels unless ``check`` is False, for callers that
        check a reduced copy instead (NaN and inf survive averaging) and call
        :meth:`check_finite` when that finds one.
        """
        img = self.read_raw(k)
        # converted values are computed in place, so they need their own copy
        a = np.asarray(img, dtype=np.float32) if self.values == "attenuation" else np.array(img, dtype=np.float32)
        if check or self.values != "attenuation":
            self.check_finite(k, a)
        if self.values == "attenuation":
            return a
        if self.values == "raw":
            a = (a - self._dark) / self._flat
        np.maximum(a, _T_FLOOR, out=a)
        np.log(a, out=a)
        np.negative(a, out=a)
        return a

    def close(self) -> None:
        held = getattr(self._local, "tf", None)
        if held is not None and held[0] == os.getpid():
            held[1].close()
        self._local.tf = None
        fd = getattr(self._local, "fd", None)
        if fd is not None and fd[0] == os.getpid():
            os.close(fd[1])
        self._local.fd = None
