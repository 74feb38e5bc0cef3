"""Bad input to the CLI: one `latentz: error:` line naming cause and fix, exit status 2, found
before any long work, and no output left behind (issue 13, "Errors that come late")."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import tifffile
from click.testing import CliRunner
from realdata import fit3d_bead

from latentz.cli import main


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def run_process(*args):
    """The CLI as users run it (its warnings reach stderr, not pytest's recorder)."""
    command = [sys.executable, "-m", "latentz.cli", *(str(a) for a in args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=300)


def one_error_line(result, *matches):
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    assert lines[0].startswith("latentz: error:"), lines[0]
    for match in matches:
        assert match in lines[0], lines[0]


def nothing_in(folder, *keep):
    left = {p.name for p in folder.iterdir()} - set(keep)
    assert not left, left


@pytest.fixture
def stack_tif(tmp_path):
    """A 30-plane, 32 x 32 px stack of dark frames around 101 ADU."""
    rng = np.random.default_rng(0)
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, (100 + rng.poisson(1.0, (30, 32, 32))).astype(np.uint16))
    return path


def calibrate(stack, out, *extra):
    return run("calibrate", stack, "--z-start", 0, "--z-step", 10, *extra, "--out", out)


def test_wrong_output_suffix_is_refused_before_reading(tmp_path):
    out = tmp_path / "locs.txt"
    one_error_line(
        run("localize", tmp_path / "none.tif", "--calibration", tmp_path / "c.h5", "--out", out),
        "locs.txt",
        ".parquet",
    )
    nothing_in(tmp_path)  # no locs.txt, no locs.txt.chunks


def test_output_into_a_missing_folder_is_refused_and_not_created(tmp_path, stack_tif):
    one_error_line(calibrate(stack_tif, tmp_path / "nowhere" / "c.h5"), "does not exist")
    nothing_in(tmp_path, "stack.tif")


def test_unwritable_output_is_refused_before_simulating(monkeypatch):
    import latentz.simulate

    def never(*args, **kwargs):
        raise AssertionError("simulated before checking the output folder")

    monkeypatch.setattr(latentz.simulate, "write_dataset", never)
    one_error_line(run("simulate", "calibration", "--out", "/proc/x"), "Cannot write into /proc")
    assert not os.path.exists("/proc/x")


def test_offset_above_the_image_median_is_refused(tmp_path, stack_tif):
    one_error_line(calibrate(stack_tif, tmp_path / "c.h5", "--offset", 1000), "above the median")
    nothing_in(tmp_path, "stack.tif")


def test_roi_larger_than_the_images_is_refused(tmp_path, stack_tif):
    one_error_line(
        calibrate(stack_tif, tmp_path / "c.h5", "--roi-size", 33), "roi_size=33", "<= 29"
    )
    nothing_in(tmp_path, "stack.tif")


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda p: tifffile.imwrite(p, np.zeros((32, 32), np.uint16)), "single image"),
        (
            lambda p: tifffile.imwrite(p, np.zeros((150, 150, 3), np.uint8), photometric="rgb"),
            "colour (RGB)",
        ),
        (lambda p: tifffile.imwrite(p, np.zeros((0, 8, 8), np.uint16)), "holds no images"),
        (lambda p: p.write_bytes(b""), "is empty"),
    ],
    ids=["2d", "rgb", "no-images", "zero-bytes"],
)
def test_tiffs_that_are_not_stacks_are_one_clear_line(tmp_path, make, match):
    path = tmp_path / "bad.tif"
    with pytest.warns() if "no images" in match else _nothing():
        make(path)
    one_error_line(calibrate(path, tmp_path / "c.h5"), match)
    nothing_in(tmp_path, "bad.tif")


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.mark.slow
def test_ctrl_c_says_how_to_resume(tmp_path, small_microscope, small_calibration):
    cal = tmp_path / "cal.h5"
    small_calibration.save(cal)
    movie = tmp_path / "long.tif"
    # long enough that the run cannot finish between the first chunk and the signal: after
    # the first chunk (compilation) the rest goes at hundreds of frames/s
    tifffile.imwrite(movie, np.concatenate([small_microscope.gear.frames] * 25))
    out = tmp_path / "locs.parquet"
    args = [sys.executable, "-m", "latentz.cli", "localize", str(movie), "--calibration"]
    args += [str(cal), "--chunk-frames", "2", "--quiet", "--out", str(out)]

    # a terminal delivers Ctrl-C; a test run started in the background (`cmd &`) inherits SIGINT
    # ignored, and Python then never raises KeyboardInterrupt: restore the default for the CLI
    def default_sigint() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    proc = subprocess.Popen(args, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint)
    chunks = tmp_path / "locs.parquet.chunks"
    deadline = time.time() + 120
    while time.time() < deadline and not list(chunks.glob("chunk-*.parquet")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "--resume" in err.strip().splitlines()[-1]
    assert not out.exists()


@pytest.mark.realdata
@pytest.mark.parametrize("factor", [0.1, 1.0, 10.0])
def test_z_step_ten_times_off_is_one_warning_line(tmp_path, factor):
    # The widths' depth of focus over their squared in-focus width, d / sigma0^2, is 0.017 per
    # nm on this bead (100 nm pixels); a step 10x off makes it 0.0017 or 0.17, outside the
    # 0.0034..0.064 that optics of any immersion and visible wavelength allow; the right step
    # (factor 1) gives no warning.
    stack, _ = fit3d_bead()
    path = tmp_path / "bead.tif"
    tifffile.imwrite(path, stack[::2].astype(np.uint16))
    result = run_process(
        "calibrate", path, "--z-start", 0, "--z-step", 20 * factor, "--offset", 400,
        "--gain", 0.1, "--pixel-size-nm", 100, "--quiet", "--out", tmp_path / "c.h5",
    )  # fmt: skip
    lines = result.stderr.splitlines()
    warned = {
        line for line in lines if line.startswith(f"latentz: warning: z step {20 * factor:g} nm")
    }
    if factor == 1.0:
        assert not warned and not any("z step" in line for line in lines)
    else:
        assert len(warned) == 1 and "that is a z step of" in warned.pop()
    assert "Traceback" not in result.stderr


@pytest.mark.realdata
def test_one_bead_calibrates_with_defaults_and_one_line_on_nearest(tmp_path):
    stack, _ = fit3d_bead()
    path = tmp_path / "bead.tif"
    tifffile.imwrite(path, stack[::2].astype(np.uint16))
    result = run_process(
        "calibrate", path, "--z-start", -1000, "--z-step", 20, "--offset", 400, "--gain", 0.1,
        "--pixel-size-nm", 100, "--quiet", "--out", tmp_path / "c.h5",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    nearest = [line for line in result.stderr.splitlines() if "field_model='nearest'" in line]
    assert len(set(nearest)) == 1 and nearest[0].startswith("latentz: warning:")
    assert "camera: offset 400 ADU (given)" in result.stdout
    assert "shape='auto'" in result.stdout


def test_a_calibration_roi_larger_than_the_movie_names_both_sizes_and_the_fix(
    tmp_path, small_microscope, small_calibration
):
    cal = tmp_path / "cal.h5"
    small_calibration.save(cal)
    side = small_calibration.roi_size - 4  # odd, smaller than the calibration's ROI
    movie = tmp_path / "small.tif"
    tifffile.imwrite(movie, small_microscope.gear.frames[:2, :side, :side])
    out = tmp_path / "locs.parquet"
    one_error_line(
        run("localize", movie, "--calibration", cal, "--out", out),
        f"calibration's {small_calibration.roi_size} px ROI",
        f"{side} x {side} px images",
        f"--roi-size {side}",
        f"localize with roi_size={side}",
    )
    nothing_in(tmp_path, "cal.h5", "small.tif")
