"""The napari reader opens a localization file (3D points coloured by z, errors as features) and
a calibration file (particles and field maps), headless: the layers are napari's own when napari
is installed (``pip install 'latentz[napari]'``), and the manifest is valid when npe2 is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from structures import rings

from latentz.io import write_table
from latentz.viewer import get_reader

MANIFEST = Path(__file__).parents[2] / "src" / "latentz" / "viewer" / "napari.yaml"


def _as_napari_layers(layers):
    """The LayerData tuples made into napari layers, when napari is installed (no window)."""
    try:
        from napari.layers import Layer
    except ImportError:
        return None
    return [Layer.create(data, kwargs, kind) for data, kwargs, kind in layers]


def test_localizations_open_as_3d_points_coloured_by_z(tmp_path):
    rng = np.random.default_rng(2)
    locs, _ = rings(rng, n_rings=4, diameter_nm=200, precision_nm=8, per_ring=100, field_nm=3000)
    locs.loc[5, "z_nm"] = np.nan  # out of the calibrated range: not a point
    path = write_table(locs, tmp_path / "locs.parquet")
    reader = get_reader(str(path))
    assert reader is not None and get_reader(str(tmp_path / "movie.tif")) is None
    ((data, kwargs, kind),) = reader(str(path))
    kept = locs.drop(index=5)
    assert kind == "points" and data.shape == (len(kept), 3)
    np.testing.assert_array_equal(data, kept[["z_nm", "y_nm", "x_nm"]].to_numpy())
    features = kwargs["features"]
    np.testing.assert_array_equal(features["z_err_nm"], kept["z_err_nm"])
    assert kwargs["face_color"] == "z_nm"
    napari_layers = _as_napari_layers([(data, kwargs, kind)])
    if napari_layers is not None:
        (layer,) = napari_layers
        assert layer.ndim == 3 and len(layer.data) == len(kept)
        assert list(layer.features["x_err_nm"]) == list(kept["x_err_nm"])
        # colour follows z: the highest point is the last colour of the colour map
        top = int(np.argmax(kept["z_nm"]))
        np.testing.assert_allclose(layer.face_color[top], layer.face_colormap.colors[-1], atol=0.02)


def test_calibration_opens_as_particles_and_field_maps(small_calibration, tmp_path):
    path = tmp_path / "cal.h5"
    small_calibration.save(path)
    layers = get_reader(str(path))(str(path))
    kinds = [kind for _, _, kind in layers]
    assert kinds == ["image", "image", "points"]
    table = small_calibration.particles
    points, kwargs, _ = layers[-1]
    np.testing.assert_array_equal(points, table[["y_nm", "x_nm"]].to_numpy())
    assert list(kwargs["features"]["culled"]) == list(table["culled"])
    # linear interpolation between the kept particles stays within their values
    kept = table[~table["culled"]]
    for (image, _, _), column in zip(layers[:2], ("sigma_z", "z_f_nm"), strict=True):
        finite = image[np.isfinite(image)]
        assert finite.size > 0.3 * image.size
        assert (
            kept[column].min() - 1e-6 <= finite.min() <= finite.max() <= kept[column].max() + 1e-6
        )
    _as_napari_layers(layers)


def test_the_manifest_is_valid_for_napari():
    npe2 = pytest.importorskip("npe2", reason="npe2 (napari's plugin engine) is not installed")
    manifest = npe2.PluginManifest.from_file(MANIFEST)
    (reader,) = manifest.contributions.readers
    assert reader.command == "latentz.get_reader"
    (command,) = manifest.contributions.commands
    module, _, function = command.python_name.partition(":")
    assert callable(getattr(__import__(module, fromlist=[function]), function))
