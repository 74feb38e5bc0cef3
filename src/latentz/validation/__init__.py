"""An independent validation microscope: other optics code, other aberration fields.

Truth for the widefield models that latentz's own simulator cannot give: this microscope shares
no code with :mod:`latentz.simulate` or :mod:`latentz._shared.zernike` (see :mod:`.microscope`),
and its aberrations vary across the field as smooth random fields with a local defect, not as
polynomials (:mod:`.fields`). :mod:`.datasets` makes calibration stacks and test frames;
:mod:`.truth` scores localizations against the truth.

Single molecules are scored apart: :mod:`.challenge` matches localizations to true emitters as the
SMLM 2016 challenge does, and :mod:`.molecules` localizes the molecules of
:mod:`latentz.simulate.molecules` with a bead calibration of the same simulated microscope.
"""

from latentz.validation.datasets import SIZES, ValidationData, make_data
from latentz.validation.fields import MODES, AberrationFields
from latentz.validation.microscope import POLYNOMIALS, Microscope, bead_slices

__all__ = [
    "SIZES",
    "MODES",
    "POLYNOMIALS",
    "AberrationFields",
    "Microscope",
    "ValidationData",
    "bead_slices",
    "make_data",
]
