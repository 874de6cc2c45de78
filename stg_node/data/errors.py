"""The one error type every loader raises for bad input: it names the file and what was expected.

Loaders never let a bare ``KeyError``, ``cv2.error`` or ``None`` image escape: a user with a
broken capture must learn which file is wrong and what the loader wanted instead.
"""

from __future__ import annotations

from pathlib import Path


class DatasetError(ValueError):
    """A dataset on disk does not match the layout a loader expects.

    ``path`` is the file or folder at fault; ``expected`` says what should have been there.
    """

    def __init__(self, path: str | Path | None, problem: str, expected: str | None = None):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.expected = expected
        where = f"{self.path}: " if self.path is not None else ""
        wanted = f" (expected {expected})" if expected else ""
        super().__init__(f"{where}{problem}{wanted}")
