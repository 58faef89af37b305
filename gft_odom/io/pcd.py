"""PCD (Point Cloud Data, v0.7) files: one numpy structured array, one binary write.

PCL, Open3D (`open3d.t.io.read_point_cloud` keeps custom fields as attributes) and CloudCompare
read them. `frequency_cloud` is the layout `gft-odom frequencies` writes: x y z intensity
frequency (float32) and band (uint8, 0 = no spectrum). Writes are atomic (temp file beside the
target, then rename), so a killed run never leaves half a cloud under a final name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gft_odom.errors import GftOdomError
from gft_odom.io.atomic import write_atomic

FREQUENCY_CLOUD_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                  ('intensity', '<f4'), ('frequency', '<f4'), ('band', 'u1')])

# The header comment that names the frame of the points.
FRAME_COMMENT = '# frame_id'
# numpy kind -> PCD TYPE letter
_PCD_TYPE = {'f': 'F', 'u': 'U', 'i': 'I'}
_NUMPY_KIND = {v: k for k, v in _PCD_TYPE.items()}


class PcdError(GftOdomError):
    """A PCD file cannot be written or read."""


def frequency_cloud(points_xyz: np.ndarray, intensity: np.ndarray | None,
                    nu: np.ndarray, band: np.ndarray) -> np.ndarray:
    """(N,) structured array of FREQUENCY_CLOUD_DTYPE; intensity None -> 0."""
    n = points_xyz.shape[0]
    if nu.shape != (n,) or band.shape != (n,):
        raise PcdError(f'{n} points but {nu.shape[0]} frequencies and {band.shape[0]} bands')
    if n and (band.min() < 0 or band.max() > np.iinfo(np.uint8).max):
        raise PcdError(f'band numbers {band.min()}..{band.max()} do not fit the uint8 band field')
    cloud = np.zeros(n, dtype=FREQUENCY_CLOUD_DTYPE)
    cloud['x'], cloud['y'], cloud['z'] = points_xyz.T
    if intensity is not None:
        cloud['intensity'] = intensity
    cloud['frequency'] = nu
    cloud['band'] = band
    return cloud


def pcd_header(dtype: np.dtype, n_points: int, data: str = 'binary',
               frame_id: str | None = None) -> str:
    """The v0.7 header of an unorganised cloud (HEIGHT 1) of `dtype` records; `frame_id`, the
    frame its points are in, goes in a comment line (`# frame_id odom`) PCL ignores."""
    names, sizes, types = [], [], []
    for name in dtype.names:
        field = dtype.fields[name][0]
        if field.kind not in _PCD_TYPE or field.shape:
            raise PcdError(f'field {name!r} has type {field}; PCD takes scalar int/uint/float')
        names.append(name)
        sizes.append(str(field.itemsize))
        types.append(_PCD_TYPE[field.kind])
    frame = f'{FRAME_COMMENT} {frame_id}\n' if frame_id else ''
    return ('# .PCD v0.7 - Point Cloud Data file format\n' + frame +
            'VERSION 0.7\n'
            f'FIELDS {" ".join(names)}\n'
            f'SIZE {" ".join(sizes)}\n'
            f'TYPE {" ".join(types)}\n'
            f'COUNT {" ".join("1" for _ in names)}\n'
            f'WIDTH {n_points}\n'
            'HEIGHT 1\n'
            'VIEWPOINT 0 0 0 1 0 0 0\n'
            f'POINTS {n_points}\n'
            f'DATA {data}\n')


def write_pcd(path: str | Path, cloud: np.ndarray, frame_id: str | None = None) -> None:
    """Write a structured array as a binary little-endian PCD file, atomically."""
    path = Path(path)
    packed = np.ascontiguousarray(cloud, dtype=_little_endian_packed(cloud.dtype))
    payload = (pcd_header(packed.dtype, packed.shape[0], frame_id=frame_id).encode('ascii')
               + packed.tobytes())
    try:
        write_atomic(path, lambda f: f.write(payload))
    except OSError as exc:
        raise PcdError(f'cannot write {path}: {exc}') from exc


def read_pcd_frame_id(path: str | Path) -> str | None:
    """The frame a PCD written with a `frame_id` says its points are in (None: it does not)."""
    try:
        with open(path, 'rb') as f:
            for _ in range(16):  # the comments come before DATA, at the top
                line = f.readline().decode('ascii', errors='replace').strip()
                if line.startswith(FRAME_COMMENT + ' '):
                    return line[len(FRAME_COMMENT):].strip() or None
                if line.upper().startswith('DATA'):
                    break
    except OSError as exc:
        raise PcdError(f'cannot read {path}: {exc}') from None
    return None


def read_pcd(path: str | Path) -> np.ndarray:
    """A binary or ASCII PCD file (COUNT 1 fields) as a structured array."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise PcdError(f'cannot read {path}: {exc}') from None
    header: dict[str, list[str]] = {}
    offset = 0
    while 'DATA' not in header:
        end = raw.find(b'\n', offset)
        if end < 0:
            raise PcdError(f'{path}: no DATA line in the PCD header')
        line = raw[offset:end].decode('ascii', errors='replace').strip()
        offset = end + 1
        if line and not line.startswith('#'):
            key, *values = line.split()
            header[key.upper()] = values
    try:
        names, sizes, types = header['FIELDS'], header['SIZE'], header['TYPE']
        counts = header.get('COUNT', ['1'] * len(names))
        n_points = int(header['POINTS'][0])
    except (KeyError, IndexError, ValueError) as exc:
        raise PcdError(f'{path}: incomplete PCD header ({exc})') from None
    if any(c != '1' for c in counts) or not len(names) == len(sizes) == len(types):
        raise PcdError(f'{path}: only COUNT 1 fields are supported')
    dtype = np.dtype([(n, f'<{_NUMPY_KIND[t]}{s}') for n, s, t in zip(names, sizes, types)])
    data = header['DATA'][0].lower()
    if data == 'binary':
        body = raw[offset:offset + n_points * dtype.itemsize]
        if len(body) != n_points * dtype.itemsize:
            raise PcdError(f'{path}: truncated ({len(body)} of {n_points * dtype.itemsize} '
                           'data bytes)')
        return np.frombuffer(body, dtype=dtype).copy()
    if data == 'ascii':
        rows = np.loadtxt(raw[offset:].decode('ascii').splitlines(), ndmin=2)
        cloud = np.zeros(rows.shape[0], dtype=dtype)
        for k, name in enumerate(names):
            cloud[name] = rows[:, k]
        return cloud
    raise PcdError(f'{path}: DATA {data} is not supported (binary or ascii)')


def _little_endian_packed(dtype: np.dtype) -> np.dtype:
    return np.dtype([(name, dtype.fields[name][0].newbyteorder('<')) for name in dtype.names])
