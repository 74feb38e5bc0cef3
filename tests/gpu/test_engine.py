"""`device` resolution: "cpu", "cuda" and "auto", with and without a usable GPU."""

import subprocess
import sys
import warnings

import pytest

from latentz._shared import engine


@pytest.fixture
def no_gpu(monkeypatch):
    monkeypatch.setattr(engine, "cuda_status", lambda: "no CUDA GPU or driver was found")
    engine._warn_cpu_fallback.cache_clear()
    yield
    engine._warn_cpu_fallback.cache_clear()


def test_cpu_is_always_the_cpu():
    assert engine.resolve_device("cpu") == "cpu"


def test_cuda_without_a_gpu_is_one_clear_error_naming_the_fix(no_gpu):
    with pytest.raises(ValueError, match=r"no CUDA GPU.*pip install 'latentz\[gpu\]'"):
        engine.resolve_device("cuda")


def test_auto_without_a_gpu_uses_the_cpu_and_says_so_once(no_gpu):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert [engine.resolve_device("auto") for _ in range(3)] == ["cpu"] * 3
    assert len(caught) == 1
    assert "using the CPU" in str(caught[0].message)


def test_auto_with_a_gpu_uses_it(monkeypatch):
    monkeypatch.setattr(engine, "cuda_status", lambda: None)
    assert engine.resolve_device("auto") == "cuda"


@pytest.mark.parametrize("bad", ["gpu", "CUDA", 0])
def test_unknown_device_is_refused(bad):
    with pytest.raises((ValueError, TypeError), match="device"):
        engine.resolve_device(bad)


def test_fit_rois_refuses_cuda_without_a_gpu_before_fitting(no_gpu):
    import numpy as np

    from latentz.fit import fit_rois

    with pytest.raises(ValueError, match="latentz\\[gpu\\]"):
        fit_rois(np.ones((2, 5, 5)), device="cuda")


def test_cli_device_cuda_without_a_gpu_is_one_line_and_status_2(no_gpu, tmp_path):
    from click.testing import CliRunner

    from latentz.cli import main

    result = CliRunner().invoke(
        main,
        ["localize", str(tmp_path / "m.tif"), "--calibration", str(tmp_path / "c.h5"),
         "--out", str(tmp_path / "o.parquet"), "--device", "cuda"],
    )  # fmt: skip
    assert result.exit_code == 2
    assert "latentz: error: device='cuda'" in result.output
    assert "Traceback" not in result.output


def test_importing_latentz_does_not_import_numba_cuda():
    code = (
        "import sys, latentz, latentz.fit, latentz.localization, latentz.calibration, "
        "latentz.cli; import latentz as lz; lz.fit_rois; lz.localize; "
        "print(sorted(m for m in sys.modules if m.startswith(('numba.cuda', 'numba_cuda'))))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"
