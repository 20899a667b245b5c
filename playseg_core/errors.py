"""The root of playseg's errors: what bad input, output or settings raise.

Every module's error class (DatasetError, BagError, MappingError, ...) subclasses `PlaysegError`, and a
check without a class of its own raises `PlaysegError` itself. The command line turns a PlaysegError (or
an OSError) into one line naming the path, topic, field or option; any other exception is a bug and keeps
its traceback. PlaysegError is also a ValueError, so code that caught ValueError around playseg's checks
keeps working.
"""

from __future__ import annotations


class PlaysegError(ValueError):
    """An expected failure: bad input, output or settings, said in one line."""
