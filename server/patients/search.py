"""Accent-insensitive patient search: names are folded once, when written, to a key that both SQLite and
PostgreSQL compare with a plain LIKE ("Jurgen" and "jürgen" find "Jürgen"; "Sorensen" finds "Sørensen")."""

from __future__ import annotations

import unicodedata

# Letters that Unicode does not decompose into a base letter and a combining mark.
_NOT_DECOMPOSED = str.maketrans({"ø": "o", "ł": "l", "đ": "d", "ħ": "h", "ı": "i", "æ": "ae", "œ": "oe", "þ": "th"})


def fold(text: str) -> str:
    """Lower case without accents: "Jürgen Ærø" -> "jurgen aero"."""
    decomposed = unicodedata.normalize("NFKD", text.casefold().translate(_NOT_DECOMPOSED))
    return "".join(char for char in decomposed if not unicodedata.combining(char))


def search_key(name: str, identifier: str) -> str:
    return f"{fold(name)} {fold(identifier)}"
