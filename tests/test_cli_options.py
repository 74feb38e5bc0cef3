import json

import numpy as np
import pytest
import tifffile

from latentz.cli.options import camera_from_options, z_positions


def test_camera_from_file_and_overrides(tmp_path):
    tifffile.imwrite(tmp_path / "flat.tif", np.full((4, 4), 2.0, np.float32))
    (tmp_path / "cam.json").write_text(
        json.dumps({"offset": 400, "gain": 0.1, "pixel_size_nm": 110, "flatfield": "flat.tif"})
    )
    cam = camera_from_options(tmp_path / "cam.json", gain=0.2)
    assert (cam.offset, cam.gain, cam.pixel_size_nm) == (400.0, 0.2, 110.0)
    np.testing.assert_array_equal(cam.flatfield, 2.0)
    assert camera_from_options(None) is None


@pytest.mark.parametrize(
    ("text", "match"),
    [("{bad", "not valid JSON"), ("[1, 2]", "JSON object"), ('{"gian": 1}', "unknown key")],
)
def test_bad_camera_files(tmp_path, text, match):
    (tmp_path / "cam.json").write_text(text)
    with pytest.raises(ValueError, match=match):
        camera_from_options(tmp_path / "cam.json")


def test_missing_camera_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="camera file"):
        camera_from_options(tmp_path / "none.json")


def test_non_positive_gain_from_options():
    with pytest.raises(ValueError, match="gain"):
        camera_from_options(None, gain=0.0)


def test_emccd_halves_the_datasheet_gain_and_readnoise(tmp_path):
    """--emccd: a given gain and read noise (options or file) become Camera.emccd's
    Poisson-equivalent values; what comes from the calibration (``base``) or from the stacks'
    photon-transfer curve is Poisson-equivalent already and stays; the line says which."""
    from latentz.camera import Camera
    from latentz.camera.source import camera_for_stacks

    cam = camera_from_options(None, offset=100.0, gain=0.1, readnoise=0.5, emccd=True)
    assert cam == Camera.emccd(offset=100.0, gain=0.1, readnoise=0.5)
    assert (cam.gain, cam.readnoise) == (0.05, 0.25)
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"gain": 0.2}))
    assert camera_from_options(path, emccd=True).gain == 0.1
    base = Camera(offset=100.0, gain=0.3, readnoise=0.4)
    assert camera_from_options(None, offset=90.0, emccd=True, base=base) == Camera(
        offset=90.0, gain=0.3, readnoise=0.4
    )
    rng = np.random.default_rng(0)
    stacks = [rng.poisson(rng.uniform(5, 500, (1, 16, 16)) * np.ones((6, 1, 1))) + 100.0]
    given = {"offset": 100.0, "gain": 0.1, "readnoise": None, "pixel_size_nm": 100.0}
    camera, said = camera_for_stacks(stacks, None, given, emccd=True)
    assert camera.gain == 0.05 and camera.readnoise == Camera().readnoise
    assert "gain 0.05 e-/ADU (given, halved: EMCCD)" in said
    assert "readnoise 1.5 e- (default)" in said


def test_z_from_start_and_step():
    np.testing.assert_allclose(z_positions(3, z_start_nm=-100, z_step_nm=50), [-100, -50, 0])


def test_z_from_file(tmp_path):
    (tmp_path / "z.txt").write_text("# piezo nm\n-10\n0\n10.5\n")
    np.testing.assert_allclose(z_positions(3, z_file=tmp_path / "z.txt"), [-10, 0, 10.5])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({}, "--z-start"),
        ({"z_start_nm": 0.0}, "--z-start"),
        ({"z_start_nm": 0.0, "z_step_nm": 0.0}, "z_step_nm"),
        ({"z_start_nm": 0.0, "z_step_nm": -5.0}, "z_step_nm"),
    ],
)
def test_bad_z_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        z_positions(4, **kwargs)


def test_z_file_length_must_match(tmp_path):
    (tmp_path / "z.txt").write_text("1\n2\n")
    with pytest.raises(ValueError, match="3 planes but 2"):
        z_positions(3, z_file=tmp_path / "z.txt")


def test_stage_offsets(tmp_path):
    from latentz.cli.options import stage_offsets_px

    (tmp_path / "o.csv").write_text("# x,y\n0,0\n512,0\n")
    np.testing.assert_array_equal(stage_offsets_px(tmp_path / "o.csv", 2), [[0, 0], [512, 0]])
    with pytest.raises(ValueError, match="must hold 3 finite"):
        stage_offsets_px(tmp_path / "o.csv", 3)
    with pytest.raises(FileNotFoundError, match="stage-offset"):
        stage_offsets_px(tmp_path / "none.csv", 2)
