"""The base of every JSON file uncertsplat writes: one pydantic model used to write *and* read it.

Each output file has exactly one model (a subclass of :class:`SchemaFile`). Writers build the model and
call :meth:`SchemaFile.write`; readers call :meth:`SchemaFile.read`, which validates the whole file, so
no reader ever guesses a key name. Every file carries ``schema_version``. Reading a file written with
an older version converts it when a conversion is defined (``_upgrade``) and otherwise fails with one
message naming the file, the version found and the version expected; a missing, renamed or extra key
fails with one message naming the file and the key.
"""

from __future__ import annotations

import json
import math
import typing
from pathlib import Path
from typing import Any, ClassVar, Self

from pydantic import BaseModel, ConfigDict, ValidationError

from uncertsplat.errors import UserError


def finite_or_none(v: Any) -> Any:
    """``None`` for a non-finite float (JSON has no NaN/inf), the value otherwise."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def path_from(folder: str | Path, target: str | Path) -> str | None:
    """``target`` relative to ``folder`` (both resolved), as a record keeps a place it points at beside its own
    (``RunScene.scene_from_run``, ``PruneReport.source_from_run``); None where there is no such path (another drive)."""
    import os

    try:
        return os.path.relpath(Path(target).resolve(), Path(folder).resolve())
    except ValueError:
        return None


def resolve_from(folder: str | Path, relative: str) -> Path:
    """The place ``relative`` (``path_from``'s) names from where ``folder`` is now (a record moved with what it points
    at finds it there)."""
    import os

    return Path(os.path.normpath(Path(folder).resolve() / relative))


class Strict(BaseModel):
    """A nested record: unknown keys are errors, non-finite floats are written as ``null``."""

    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="null")


def describe_validation_error(err: ValidationError, limit: int = 3) -> str:
    """``key 'a.b': what is wrong`` for the first ``limit`` problems of a pydantic error."""
    parts = []
    for e in err.errors()[:limit]:
        loc = ".".join(str(x) for x in e["loc"]) or "(top level)"
        kind = e["type"]
        if kind == "missing":
            parts.append(f"key '{loc}' is missing")
        elif kind == "extra_forbidden":
            parts.append(f"key '{loc}' is not part of the schema")
        else:
            parts.append(f"key '{loc}': {e['msg']} (found {e.get('input')!r:.60})")
    more = len(err.errors()) - limit
    if more > 0:
        parts.append(f"and {more} more")
    return "; ".join(parts)


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The pydantic models a field annotation can hold (``M``, ``M | None``, ``list[M]``, ``dict[str, M]``)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]


def key_problems(model: type[BaseModel], data: Any, prefix: str = "") -> list[str]:
    """Keys of ``model`` (and of the records nested in it) absent from ``data``, and keys it does not know.

    Writers dump every field, so a key missing from a file is a damaged or foreign file, never a default:
    readers check this before validating, which would otherwise fill the default in silently.
    """
    if not isinstance(data, dict):
        return []
    out = [f"key '{prefix}{k}' is not part of the schema" for k in data if k not in model.model_fields]
    for name, field in model.model_fields.items():
        if name not in data:
            out.append(f"key '{prefix}{name}' is missing")
            continue
        value = data[name]
        for sub in _models_in(field.annotation)[:1]:
            if isinstance(value, dict) and typing.get_origin(field.annotation) is dict:
                for k, v in value.items():
                    out += key_problems(sub, v, f"{prefix}{name}.{k}.")
            elif isinstance(value, list):
                for i, v in enumerate(value):
                    out += key_problems(sub, v, f"{prefix}{name}.{i}.")
            else:
                out += key_problems(sub, value, f"{prefix}{name}.")
    return out


def run_file_hint(name: str) -> str:
    """The advice for a run's ``name`` (config.json, scene.json) found damaged: ``train`` (or ``prune``, for a pruned
    run) writes it when the run starts, and every command reads it first, ``train --resume`` included, so none of them
    gets as far as writing it again."""
    return (f"A run's {name} is written when its training (or prune) starts and read first by every command, `train "
            "--resume` included: put back a copy of the file, or make the run again into a new folder (`uncertsplat "
            "train SCENE -o NEW_RUN`" + (", with `--config RUN/config.json` for the same settings" if name != "config.json"
                                          else "") + "; a pruned run: `uncertsplat prune SOURCE_RUN -o NEW`).")


class SchemaFile(Strict):
    """A JSON file with a schema version. Subclasses set ``FILE_NAME`` and ``SCHEMA_VERSION``.

    Subclasses declare ``schema_version: int = SCHEMA_VERSION`` themselves, so each file's current
    version is written with it.
    """

    FILE_NAME: ClassVar[str] = ""
    SCHEMA_VERSION: ClassVar[int] = 1
    WRITTEN_BY: ClassVar[str] = "uncertsplat"
    DAMAGED_HINT: ClassVar[str | None] = None
    """What to do when the file is damaged or of an old layout, where re-running ``WRITTEN_BY`` cannot write it
    again (a run's files, written when its training starts: ``run_file_hint``); None: re-run ``WRITTEN_BY``."""
    """The command that writes the file (named in errors: re-running it rewrites the file)."""

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        """Convert the JSON of an older ``version`` (0: no ``schema_version`` key) to the current layout;
        None when it cannot be converted."""
        return None

    # ------------------------------------------------------------------------------------------ reading
    @classmethod
    def from_dict(cls, data: Any, *, source: str | Path | None = None) -> Self:
        """Validate parsed JSON, upgrading an older schema version when a conversion exists.

        Raises:
            UserError: naming ``source`` (or the file kind) and the version or key that is wrong, or what the file is
                when it is another of the records uncertsplat writes (``_refuse_another_kind``).
        """
        try:
            return cls._from_dict(data, source=source)
        except UserError:
            cls._refuse_another_kind(data, Path(source) if source is not None else None)
            raise

    @classmethod
    def _from_dict(cls, data: Any, *, source: str | Path | None = None) -> Self:
        """``from_dict`` for a file of this kind."""
        where = Path(source) if source is not None else None
        label = cls.FILE_NAME or cls.__name__
        hint = cls.DAMAGED_HINT or f"Re-run `{cls.WRITTEN_BY}` to write it again with this version of uncertsplat."
        if not isinstance(data, dict):
            raise UserError(f"{label}: expected a JSON object, found {type(data).__name__}", path=where, hint=hint)
        # Files written before schemas were versioned have no key: version 0 (converted where possible).
        version = data.get("schema_version", 0)
        if not isinstance(version, int) or isinstance(version, bool):
            raise UserError(f"{label}: 'schema_version' must be an integer, found {version!r}", path=where, hint=hint)
        if version > cls.SCHEMA_VERSION:
            raise UserError(f"{label}: schema version {version} is newer than the {cls.SCHEMA_VERSION} this version "
                            f"of uncertsplat reads", path=where, hint="Upgrade uncertsplat to read it.")
        if version < cls.SCHEMA_VERSION:
            upgraded = cls._upgrade(dict(data), version)
            if upgraded is None:
                # (the error names the file itself when it has one: its name in the message said it twice)
                what = "the file" if where is not None else label
                found = (f"{what} has no 'schema_version' (written before files were versioned, or edited)"
                         if "schema_version" not in data else f"{what}'s schema version {version}")
                raise UserError(f"{found}: it is older than version {cls.SCHEMA_VERSION} and cannot be converted",
                                path=where, hint=hint)
            data = {**upgraded, "schema_version": cls.SCHEMA_VERSION}
        else:
            problems = key_problems(cls, data)
            if problems:
                more = f"; and {len(problems) - 4} more" if len(problems) > 4 else ""
                raise UserError(f"{label} does not match its schema (version {cls.SCHEMA_VERSION}): "
                                + "; ".join(problems[:4]) + more, path=where, hint=hint)
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise UserError(f"{label} does not match its schema (version {cls.SCHEMA_VERSION}): "
                            f"{describe_validation_error(err)}", path=where, hint=hint) from None

    @classmethod
    def _refuse_another_kind(cls, data: dict, where: Path | None) -> None:
        """Refuse, in one sentence, a file of another kind (``metrics.json`` read as a ``Selection``: "schema version
        4 is newer than the 2 this version of uncertsplat reads. Upgrade uncertsplat"; a synthetic scene's
        ``scene.json`` read as a run's: a key missing, "re-run `uncertsplat train`"): one that lacks a key this schema
        requires and that ``schemas.identify.what_file_is`` tells as another record, asked only of a file that could
        not be read (a file of this kind with a key missing keeps ``_from_dict``'s message)."""
        from uncertsplat.schemas.identify import identifying_keys, own_words, what_file_is

        if not isinstance(data, dict) or identifying_keys(cls) <= set(data):
            return
        other, mine = what_file_is(data), own_words(cls)
        if other is None or mine is None or other == mine or other.startswith("a record uncertsplat writes"):
            return
        raise UserError(f"this is {other}, not {mine}", path=where,
                        hint=f"Read it with its own schema (README, \"Outputs and their schemas\"), or give the "
                             f"{cls.FILE_NAME or cls.__name__} that `{cls.WRITTEN_BY}` writes.")

    @classmethod
    def read(cls, path: str | Path) -> Self:
        """Read and validate ``path``.

        Raises:
            UserError: when the file is missing, is not JSON, or does not match the schema.
        """
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise UserError(f"{cls.FILE_NAME or cls.__name__} not found", path=path,
                            hint=f"It is written by `{cls.WRITTEN_BY}`.") from None
        except (OSError, UnicodeDecodeError) as err:
            raise UserError(f"cannot be read ({err})", path=path) from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise UserError(f"not valid JSON ({err})", path=path,
                            hint=cls.DAMAGED_HINT or f"The file is damaged; re-run `{cls.WRITTEN_BY}`.") from None
        return cls.from_dict(data, source=path)

    @classmethod
    def read_optional(cls, path: str | Path) -> Self | None:
        """``read(path)``, or None when the file does not exist (any other problem still raises)."""
        return cls.read(path) if Path(path).is_file() else None

    # ------------------------------------------------------------------------------------------ writing
    def to_json(self) -> str:
        """Pretty JSON text of the file."""
        return self.model_dump_json(indent=2)

    def write(self, path: str | Path) -> Path:
        """Write atomically (temp file + rename) to ``path``."""
        from uncertsplat.io.atomic import atomic_write_text

        return atomic_write_text(Path(path), self.to_json() + "\n")
