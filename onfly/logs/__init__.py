"""OnFly logs: the documented on-disk format, a streaming writer and a reader.

See :mod:`onfly.logs.format` for the layout.
"""

from onfly.logs.format import LogCorruptError, LogError, LogEvent, LogExistsError, LogFormatError, is_log_dir
from onfly.logs.reader import LogFrame, LogReader
from onfly.logs.writer import LogWriter, LogWriterConfig

__all__ = [
    "LogCorruptError",
    "LogError",
    "LogEvent",
    "LogExistsError",
    "LogFormatError",
    "LogFrame",
    "LogReader",
    "LogWriter",
    "LogWriterConfig",
    "is_log_dir",
]
