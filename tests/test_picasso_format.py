import h5py
import numpy as np
import pandas as pd
import pytest
import yaml

from latentz.io.picasso import PICASSO_FIELDS, write_picasso


def _locs(n=5):
    rng = np.random.default_rng(3)
    return pd.DataFrame(
        {
            "frame": np.arange(n),
            "x": rng.uniform(0, 64, n),
            "y": rng.uniform(0, 64, n),
            "photons": rng.uniform(1e3, 1e4, n),
            "wx": rng.uniform(1, 2, n),
            "wy": rng.uniform(1, 2, n),
            "background": rng.uniform(5, 10, n),
            "x_err": rng.uniform(0.01, 0.05, n),
            "y_err": rng.uniform(0.01, 0.05, n),
            "z_nm": rng.uniform(-500, 500, n),
        }
    )


def test_picasso_schema(tmp_path):
    locs = _locs()
    h5, yml = write_picasso(
        locs,
        tmp_path / "locs.hdf5",
        width=64,
        height=64,
        n_frames=5,
        pixel_size_nm=130.0,
        info={"calibration": "cal.h5"},
    )
    with h5py.File(h5) as handle:
        records = handle["locs"][...]
    assert records.dtype.names == tuple(name for name, _, _ in PICASSO_FIELDS)
    for name, col, _ in PICASSO_FIELDS:
        np.testing.assert_allclose(records[name], locs[col], rtol=1e-6)
    docs = list(yaml.safe_load_all(yml.read_text()))
    assert docs[0]["Width"] == 64 and docs[0]["Frames"] == 5 and docs[0]["Pixelsize"] == 130.0
    assert docs[1]["calibration"] == "cal.h5"


def test_picasso_loader_reads_it_when_installed(tmp_path):
    picasso_io = pytest.importorskip("picasso.io", reason="picassosr is not installed here")
    h5, _ = write_picasso(
        _locs(), tmp_path / "locs.hdf5", width=64, height=64, n_frames=5, pixel_size_nm=130.0
    )
    locs, info = picasso_io.load_locs(str(h5))
    assert len(locs) == 5 and info[0]["Width"] == 64


def test_picasso_errors(tmp_path):
    with pytest.raises(ValueError, match="missing column"):
        write_picasso(
            _locs().drop(columns="z_nm"),
            tmp_path / "a.hdf5",
            width=1,
            height=1,
            n_frames=1,
            pixel_size_nm=1.0,
        )
    with pytest.raises(ValueError, match=".hdf5"):
        write_picasso(_locs(), tmp_path / "a.h5", width=1, height=1, n_frames=1, pixel_size_nm=1.0)
