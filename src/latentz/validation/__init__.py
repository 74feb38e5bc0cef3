"""Independent validation microscopes: other optics code, other aberration fields.

Truth for the widefield models that latentz's own simulator cannot give: this package shares no
code with :mod:`latentz.simulate` or :mod:`latentz._shared.zernike` (see :mod:`.microscope`), and
its aberrations vary across the field as polynomials, smooth random fields or fields with local
defects (:mod:`.fields`). :mod:`.datasets` makes calibration stacks and test frames;
:mod:`.family` draws whole microscopes at random; :mod:`.truth` scores localizations against
the truth from geometry; :mod:`.floor` gives each study's oracle floor.

Single molecules are scored apart: :mod:`.challenge` matches localizations to true emitters as the
SMLM 2016 challenge does, and :mod:`.molecules` localizes the molecules of
:mod:`latentz.simulate.molecules` with a bead calibration of the same simulated microscope.
"""

from latentz.validation.datasets import SIZES, ValidationData, make_data
from latentz.validation.family import FAMILY_SIZES, Draw, draw_microscope, family_data
from latentz.validation.fields import FORMS, MODES, AberrationFields
from latentz.validation.microscope import POLYNOMIALS, Microscope, bead_slices

__all__ = [
    "FAMILY_SIZES",
    "FORMS",
    "SIZES",
    "Draw",
    "draw_microscope",
    "family_data",
    "MODES",
    "POLYNOMIALS",
    "AberrationFields",
    "Microscope",
    "ValidationData",
    "bead_slices",
    "make_data",
]
