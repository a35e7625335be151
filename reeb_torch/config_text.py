"""REEB's settings from text: a preset, a JSON config file and ``FIELD=VALUE`` pairs.

What ``reeb propose --preset/--config/--set/--top-k`` reads, for scripts and benchmarks:

>>> from reeb_torch.config_text import config_from
>>> cfg = config_from("default", "tuned.json", ["class_quota={\\"Pedestrian\\": 0.2}", "use_regions=off"])

A bool field takes true/false, yes/no, on/off or 1/0; a field of named choices takes one of
its words as written (``shadow_score=none`` is the word ``'none'``, not None); a free-text
field its text (``ranker=none``, ``ranker=mine.safetensors``); other fields take JSON (``3``,
``1.5``, ``[1, 2]``, ``null``) or a bare string. A field may be named with its part
(``nms.top_k=500``, :data:`~reeb_torch.config.PART_OF`). A config file's relative ``ranker`` is read
from the file's folder (as ``reeb fit`` writes it). Every refusal is a :class:`SettingError`
naming what was wrong.
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .config import PART_FIELDS, PART_OF, ReebConfig, get_preset
from .ranker import SHIPPED

__all__ = ["SettingError", "BOOL_WORDS", "config_from", "parse_sets", "read_config_file"]


class SettingError(ValueError):
    """A setting that cannot be read or is refused; :attr:`option` says where it came from
    (``"--set"``, ``"--config"``, or ``"--config/--set/--top-k"`` for the whole)."""

    def __init__(self, message: str, option: str) -> None:
        super().__init__(message)
        self.option = option


BOOL_WORDS = {"true": True, "yes": True, "on": True, "1": True,
              "false": False, "no": False, "off": False, "0": False}
"""The words a bool field takes (case-insensitive)."""


def config_from(preset: str = "default", config_file: str | os.PathLike | None = None,
                sets: Sequence[str] = (), top_k: int | None = None) -> ReebConfig:
    """The :class:`~reeb_torch.ReebConfig` of ``preset``, then the fields of ``config_file``
    (:func:`read_config_file`), then ``sets`` (:func:`parse_sets`), then ``top_k``; each later
    source overrides the earlier ones.

    Raises:
        SettingError: a file that cannot be read, a pair that cannot be parsed, an unknown
            field or a value ReebConfig refuses (one line each).
    """
    d = get_preset(preset).to_dict()
    if config_file is not None:
        d.update(read_config_file(config_file))
    d.update(parse_sets(sets))
    if top_k is not None:
        d["top_k"] = top_k
    try:
        return ReebConfig.from_dict(d)
    except RecursionError:
        raise SettingError("a value is nested too deeply to be a setting", "--config/--set/--top-k") from None
    except (TypeError, ValueError, ArithmeticError) as e:
        raise SettingError(" ".join(str(e).split()) or type(e).__name__, "--config/--set/--top-k") from None


def read_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """The ReebConfig fields of a JSON file: an object of fields, or a saved record with a
    ``"config"`` object (``reeb calibrate``'s, ``reeb tune``'s); a relative ``ranker`` taken
    from the file's folder. Whether the fields exist is :func:`config_from`'s to say.

    Raises:
        SettingError: the file cannot be read, is not JSON, or holds no object.
    """
    p = Path(path)
    try:
        loaded = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise SettingError(f"{path}: cannot read ({e})", "--config") from None
    except json.JSONDecodeError as e:
        raise SettingError(f"{path}: not valid JSON ({e})", "--config") from None
    except RecursionError:
        raise SettingError(f"{path}: nested too deeply to be a config", "--config") from None
    if isinstance(loaded, dict) and isinstance(loaded.get("config"), dict):
        loaded = loaded["config"]  # a saved record with a "config" entry
    if not isinstance(loaded, dict):
        raise SettingError(f"{path}: expected a JSON object of ReebConfig fields", "--config")
    if isinstance(loaded.get("ranker"), str):
        loaded["ranker"] = _ranker_beside(loaded["ranker"], p)
    return loaded


def parse_sets(sets: Sequence[str]) -> dict[str, Any]:
    """``FIELD=VALUE`` pairs as ReebConfig field values, each parsed by its field's type (the
    module doc). Whether the fields exist and the values are in range is ReebConfig's to say.

    Raises:
        SettingError: a pair without ``=``, a bad bool word, JSON that does not parse.
    """
    bools, words = _field_kinds() if sets else (set(), {})
    out: dict[str, Any] = {}
    for item in sets:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise SettingError(f"{item!r}: expected FIELD=VALUE, e.g. scale=1.0", "--set")
        name = _flat_name(key.strip())
        if name in bools:
            out[name] = _parse_bool(name, value)
        elif name in words and words[name] is None:
            out[name] = _parse_text(value)
        else:
            out[name] = _parse_value(value, words.get(name) or (), name)
    return out


def _flat_name(name: str) -> str:
    """The field a ``--set`` names: ``FIELD`` as it is, or ``PART.FIELD`` (``nms.top_k``) checked
    against its part."""
    part, dot, field = name.partition(".")
    if not dot:
        return name
    if part not in PART_FIELDS:
        raise SettingError(f"{name}: {part!r} is not a part of the settings; the parts are "
                           f"{', '.join(PART_FIELDS)}", "--set")
    if field not in PART_FIELDS[part]:
        where = f" (it is in {PART_OF[field]})" if field in PART_OF else ""
        raise SettingError(f"{name}: the part {part} has no field {field!r}{where}", "--set")
    return field


def _parse_value(text: str, choices: tuple[str, ...] = (), field: str = "") -> Any:
    """A value: one of the field's ``choices`` (the words of a ``Literal`` field, kept as
    written even where they read as JSON, such as ``none``), else JSON, else
    ``none``/``null`` as None, ``true``/``false``, or the bare string. A value that opens as
    JSON does (``[``, ``{``, ``"``) but does not parse is refused, naming ``field``."""
    word = text.strip()
    if word in choices:
        return word
    try:
        return json.loads(text)
    except RecursionError:
        raise SettingError(f"{text[:40]!r}...: nested too deeply to be a setting", "--set") from None
    except json.JSONDecodeError as e:
        if word[:1] in ('[', '{', '"'):
            raise SettingError(f"{field}={text[:60]!r}: not valid JSON ({e.msg} at character {e.pos + 1})",
                               "--set") from None
        low = word.lower()
        if low in ("none", "null"):
            return None
        if low in ("true", "false"):
            return low == "true"
        return text


def _parse_bool(field: str, text: str) -> bool:
    """A bool field's value: one of :data:`BOOL_WORDS`."""
    word = text.strip()
    if len(word) >= 2 and word[0] == word[-1] and word[0] in "\"'":
        word = word[1:-1].strip()  # --set 'use_regions="false"'
    try:
        return BOOL_WORDS[word.lower()]
    except KeyError:
        raise SettingError(f"{field}={text!r}: {field} is a yes/no setting; use true/false, yes/no, on/off "
                           "or 1/0", "--set") from None


def _parse_text(text: str) -> str:
    """A free-text field's value (``ranker``): the text as written, a JSON string's quotes
    removed (``ranker=none`` is the word ``'none'``, not None)."""
    word = text.strip()
    try:
        value = json.loads(word)
    except (json.JSONDecodeError, RecursionError):
        return word
    return value if isinstance(value, str) else word


def _field_kinds() -> tuple[set[str], dict[str, tuple[str, ...] | None]]:
    """Names of the ReebConfig fields whose type is ``bool``, and the words of each field
    whose type is a ``Literal`` of strings (from the dataclass); a free-text ``str`` field
    maps to ``None`` in the second (any text, taken as written)."""
    hints = typing.get_type_hints(ReebConfig)
    bools: set[str] = set()
    words: dict[str, tuple[str, ...] | None] = {}
    for f in dataclasses.fields(ReebConfig):
        hint = hints.get(f.name)
        if hint is bool:
            bools.add(f.name)
        elif typing.get_origin(hint) is typing.Literal:
            words[f.name] = tuple(a for a in typing.get_args(hint) if isinstance(a, str))
        elif hint is str:
            words[f.name] = None
    return bools, words


def _ranker_beside(ranker: str, config_file: Path) -> str:
    """A config file's ``ranker``: a relative path is taken from the config file's folder (as
    ``reeb fit`` writes it), so the config reads from any folder; a path that is found only
    from the current folder (a config written before) is kept; names and absolute paths
    are kept."""

    path = Path(os.path.expanduser(ranker))
    if ranker in SHIPPED or ranker == "none" or path.is_absolute():
        return ranker
    beside = config_file.parent / path
    return ranker if path.exists() and not beside.exists() else str(beside)
