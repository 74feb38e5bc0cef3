"""Reading and writing: images (lazy TIFF stacks), tables (Parquet, CSV) and Picasso's format."""

from latentz.io.images import as_frames, open_movie, read_frames, read_stack
from latentz.io.tables import TABLE_FORMATS, read_table, write_table

__all__ = [
    "TABLE_FORMATS",
    "as_frames",
    "open_movie",
    "read_frames",
    "read_stack",
    "read_table",
    "write_table",
]
