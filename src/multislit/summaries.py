"""Results that print as a short summary, not as screens of arrays.

A result class derives from :class:`Summarised` and defines :meth:`~Summarised.summary`;
``print(result)`` then shows the summary and ``repr(result)`` (a notebook's echo) its first
line in angle brackets. A dataclass that derives from it is declared with ``repr=False``
so that the dataclass does not write its own field-by-field repr over it.
"""

from __future__ import annotations

__all__ = ["Summarised"]


class Summarised:
    """Mixin: ``str()`` is :meth:`summary`, ``repr()`` its first line."""

    def summary(self) -> str:  # pragma: no cover - each result defines its own
        raise NotImplementedError

    def __str__(self) -> str:
        return self.summary()

    def __repr__(self) -> str:
        first = self.summary().split("\n", 1)[0]
        return f"<{type(self).__name__} {first}>"
