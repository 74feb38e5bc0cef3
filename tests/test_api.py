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
