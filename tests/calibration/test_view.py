"""CalibrationView, the calibration as the modules behind its methods read it: every member is
one that Calibration has, with the same parameters."""

import dataclasses
import inspect

from latentz.calibration.result import Calibration
from latentz.calibration.view import CalibrationView


def _members(cls: type) -> dict[str, object]:
    """The properties and methods that ``cls`` itself defines, by name (dunders aside)."""
    return {
        name: value
        for name, value in vars(cls).items()
        if isinstance(value, property) or inspect.isfunction(value)
        if not name.startswith("__")
    }


def test_calibration_has_every_member_of_the_view():
    assert dataclasses.is_dataclass(Calibration)
    fields = {f.name for f in dataclasses.fields(Calibration)}
    view = _members(CalibrationView)
    assert {"camera", "_cache", "widefield", "nearest"} <= view.keys()
    for name, member in view.items():
        if isinstance(member, property):
            assert name in fields or isinstance(getattr(Calibration, name), property), name
        else:
            own = inspect.signature(getattr(Calibration, name)).parameters
            assert list(own) == list(inspect.signature(member).parameters), name
