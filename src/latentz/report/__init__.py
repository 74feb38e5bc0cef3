"""The HTML report (:mod:`~latentz.report.html`) and its sections, one per stage
(:mod:`~latentz.report.sections`, :mod:`~latentz.report.calibration_quality`)."""

from latentz.report.html import Section, table_html, write_report

__all__ = ["Section", "table_html", "write_report"]
