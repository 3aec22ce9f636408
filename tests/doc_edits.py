"""What the document-rejection tests write into a valid document to break it."""

from __future__ import annotations


class _Delete:
    """A key to delete; its repr is stable, so the test ids are the same in every process."""

    def __repr__(self) -> str:
        return "<deleted>"


#: Put as a value: the key is removed instead.
DELETE = _Delete()
