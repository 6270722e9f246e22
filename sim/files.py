"""Files: written so that a crash or Ctrl-C never leaves half of one, and configuration read from
JSON or TOML (one helper each for the project).

``atomic_path(path)`` yields a temporary name in the same folder; when the block ends without an
exception the temporary file replaces ``path`` (``os.replace``, atomic on POSIX), otherwise it
is removed and ``path`` keeps what it held.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary file beside ``path`` (mode 0644, same suffix: some writers insist on it) that
    replaces it if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + path.suffix)
    os.close(fd)
    os.chmod(tmp, 0o644)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def sha256_file(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def is_file(source: str | Path) -> bool:
    """Whether ``source`` names an existing file; text no file name can be (inline JSON longer
    than the 255 bytes a name may have, which ``Path.is_file`` answers with OSError) is not one."""
    try:
        return Path(source).is_file()
    except (OSError, ValueError):
        return False


class ConfigFileError(ValueError):
    """A configuration that cannot be read; the message names the source, the place and the fix."""


def read_config(source: str | Path, what: str) -> dict:
    """A mapping from a ``.json`` or ``.toml`` file, or from inline JSON text (``source`` that is
    not an existing file and starts with ``{``). ``what`` names the source in errors (a flag)."""
    import json
    import tomllib

    path = Path(source)
    text = str(source).strip()
    if not is_file(path):
        if path.suffix.lower() in (".json", ".toml"):
            raise ConfigFileError(f"{what}: no file {text!r} (looked in {Path.cwd()}); check the path")
        if not text.startswith("{"):
            raise ConfigFileError(f"{what}: {text!r} is neither a file nor inline JSON; give a "
                                  ".json/.toml file or a JSON object such as '{\"lr\": 5e-4}'")
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ConfigFileError(f"{what}: inline JSON is not valid: {err}") from None
    elif path.suffix.lower() == ".toml":
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as err:
            raise ConfigFileError(f"{what}: {str(path)!r} is not valid TOML: {err}") from None
    else:
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ConfigFileError(f"{what}: {str(path)!r} is not valid JSON: {err} (a .toml file "
                                  "must end in .toml)") from None
    if not isinstance(data, dict):
        raise ConfigFileError(f"{what}: expected a mapping of fields, got {type(data).__name__}")
    return data


__all__ = ["ConfigFileError", "atomic_path", "atomic_write_bytes", "atomic_write_text", "read_config",
           "sha256_file"]
