import importlib

import latentz


def test_every_name_in_all_imports():
    for name in latentz.__all__:
        assert getattr(latentz, name) is not None, name


def test_all_has_no_duplicates_and_public_names_only():
    assert len(set(latentz.__all__)) == len(latentz.__all__)
    assert all(not n.startswith("_") or n == "__version__" for n in latentz.__all__)


def test_version_matches_installed_metadata():
    from importlib.metadata import version

    assert latentz.__version__ == version("latentz")
    assert importlib.import_module("latentz._version").__version__ == latentz.__version__


def test_all_matches_the_lazy_export_table():
    assert set(latentz.__all__) - {"__version__"} == set(latentz._EXPORTS)


def test_unknown_attribute_is_an_attribute_error():
    import pytest

    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        latentz.nope  # noqa: B018


def test_public_names_survive_importing_every_submodule_first():
    """No public function shares its name with a module: importing every submodule before the
    public API is touched must leave `lz.calibrate`, `lz.localize`, ... callable."""
    import subprocess
    import sys

    code = (
        "import pkgutil, importlib, latentz as lz\n"
        "mods = [m.name for m in pkgutil.walk_packages(lz.__path__, 'latentz.')]\n"
        "for m in mods:\n"
        "    importlib.import_module(m)\n"
        "import types\n"
        "bad = [n for n in lz.__all__ if isinstance(getattr(lz, n), types.ModuleType)]\n"
        "assert not bad, bad\n"
        "assert callable(lz.calibrate) and callable(lz.localize) and callable(lz.link)\n"
        "print(len(mods))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) > 40


def test_no_module_is_named_like_a_public_name():
    import pkgutil

    modules = {
        m.name.rsplit(".", 1)[-1] for m in pkgutil.walk_packages(latentz.__path__, "latentz.")
    }
    assert not modules & set(latentz.__all__)
