"""Reading and writing: images (lazy TIFF stacks), tables (Parquet, CSV), Picasso's and
ThunderSTORM's localization formats, and any localization file by its format."""

from latentz.io.images import as_frames, open_movie, read_frames, read_stack
from latentz.io.localizations import LOCALIZATION_SUFFIXES, read_localizations
from latentz.io.tables import TABLE_FORMATS, read_table, write_table

__all__ = [
    "LOCALIZATION_SUFFIXES",
    "TABLE_FORMATS",
    "as_frames",
    "open_movie",
    "read_frames",
    "read_localizations",
    "read_stack",
    "read_table",
    "write_table",
]
