"""Where a run folder goes: checked before the run starts, written beside the target, moved in last.

swarmpc deletes only what it created. A complete run folder carries a marker file
(:data:`MARKER`); an existing path at the target is replaced only when it is such a folder and the
caller asked for it (``overwrite``, the CLI's ``--overwrite``). Anything else there (a file, a
folder of the user's, a symbolic link) is refused with one line before any work is done. An empty
folder is taken as it is: nothing in it can be lost.

The target is reserved before the run: its parent is created, a staging folder is made inside it
(which proves the location writable) and the free space is compared with the run's expected size.
A write that fails after the run keeps the computed run elsewhere (the system's temporary folder)
and says where, so the computation is not lost with the disk.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import stat
from pathlib import Path

MARKER = ".swarmpc-run"
"""The marker file of a complete run folder: JSON with the format's name and version."""

MARKER_CONTENT = {"format": "swarmpc-run", "version": 1}

SPACE_RESERVE_BYTES = 16 * 2**20
"""Free space kept beyond a run's expected size (figures, file-system slack)."""


class OutputError(Exception):
    """The output location cannot take the run; the message is one line naming the path."""


def is_run_folder(path: Path) -> bool:
    """A real folder (not a link to one) that holds swarmpc's marker as a regular file."""
    try:
        folder = os.lstat(path)
        marker = os.lstat(path / MARKER)
    except OSError:
        return False
    return stat.S_ISDIR(folder.st_mode) and stat.S_ISREG(marker.st_mode)


def write_marker(folder: Path) -> None:
    """Mark ``folder`` as a complete swarmpc run folder (written last, after every other file)."""
    (folder / MARKER).write_text(json.dumps(MARKER_CONTENT) + "\n")


def make_folder(parent: Path, prefix: str) -> Path:
    """A new folder ``parent/prefix<random>`` with the user's usual permissions (the umask's,
    unlike :func:`tempfile.mkdtemp`'s owner-only ones)."""
    for _ in range(100):
        folder = parent / f"{prefix}{secrets.token_hex(4)}"
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        return folder
    raise FileExistsError(f"no free name for {parent / prefix}*")


def _is_empty_folder(path: Path) -> bool:
    try:
        return stat.S_ISDIR(os.lstat(path).st_mode) and not any(os.scandir(path))
    except OSError:
        return False


def normalise_target(target: str | Path) -> Path:
    """An absolute target whose last component is not resolved, so a link at the target is seen
    as a link (and refused), never followed to the folder it points to."""
    path = Path(target)
    if path.name in ("", ".", ".."):
        return path.resolve()
    return path.absolute().parent.resolve() / path.name


def refusal(target: Path, overwrite: bool) -> str | None:
    """Why an existing path at ``target`` may not be replaced (None: it may, or nothing is there)."""
    try:
        info = os.lstat(target)
    except FileNotFoundError:
        return None
    except OSError as err:
        return f"{target}: cannot inspect the output path ({err.strerror})"
    if stat.S_ISLNK(info.st_mode):
        return f"{target}: is a symbolic link; swarmpc writes run folders only to real paths"
    if _is_empty_folder(target):
        return None
    if not is_run_folder(target):
        kind = "a folder" if stat.S_ISDIR(info.st_mode) else "a file"
        return f"{target}: exists and is {kind}, not a swarmpc run folder; choose another --out"
    if not overwrite:
        return f"{target}: holds an earlier run; --overwrite replaces it"
    return None


def _first_missing(path: Path) -> Path | None:
    """The outermost folder of ``path`` that does not exist yet (None: it all exists)."""
    missing = None
    for folder in [path, *path.parents]:
        if os.path.lexists(folder):
            break
        missing = folder
    return missing


class RunFolderTarget:
    """A run folder's destination, checked and reserved before the run starts.

    Construction refuses a target that may not be replaced, creates the parent folders, makes the
    staging folder and checks the free space; :meth:`commit` moves the staging folder into place,
    :meth:`discard` removes what the reservation made.
    """

    def __init__(self, target: str | Path, overwrite: bool = False, expected_bytes: int = 0) -> None:
        self.target = normalise_target(target)
        self.overwrite = overwrite
        self.kept = False
        """Set when a failed :meth:`commit` left the finished run in the staging folder."""
        reason = refusal(self.target, overwrite)
        if reason is not None:
            raise OutputError(reason)
        parent = self.target.parent
        self._created = _first_missing(parent)
        try:
            parent.mkdir(parents=True, exist_ok=True)
            self.staging = make_folder(parent, f".{self.target.name}.partial-")
        except OSError as err:
            self._remove_created()
            raise OutputError(f"{self.target}: cannot write there ({err.strerror or err})") from None
        free = shutil.disk_usage(parent).free
        if free < expected_bytes + SPACE_RESERVE_BYTES:
            self.discard()
            raise OutputError(
                f"{self.target}: not enough free space ({free / 2**20:.0f} MiB free, the run needs "
                f"about {(expected_bytes + SPACE_RESERVE_BYTES) / 2**20:.0f} MiB)"
            )

    def commit(self) -> Path:
        """Move the finished staging folder into place (replacing an earlier run folder only
        when ``overwrite`` was given); on a refusal the staging folder is kept and named."""
        reason = refusal(self.target, self.overwrite)
        if reason is not None:
            self.kept = True
            raise OutputError(f"{reason} (the run is kept in {self.staging})")
        try:
            if is_run_folder(self.target):
                self._replace_run_folder()
            else:
                os.replace(self.staging, self.target)  # fails if a non-empty folder appeared
        except OSError as err:
            self.kept = True
            raise OutputError(
                f"{self.target}: cannot move the run into place ({err.strerror}); it is kept in {self.staging}"
            ) from None
        return self.target

    def _replace_run_folder(self) -> None:
        retired = make_folder(self.target.parent, f".{self.target.name}.old-")
        os.replace(self.target, retired / self.target.name)
        try:
            os.replace(self.staging, self.target)
        except OSError:
            os.replace(retired / self.target.name, self.target)
            retired.rmdir()
            raise
        shutil.rmtree(retired, ignore_errors=True)

    def discard(self) -> None:
        """Remove the staging folder and the parent folders this reservation created (not a
        finished run that :meth:`commit` could not move into place)."""
        if self.kept:
            return
        shutil.rmtree(self.staging, ignore_errors=True)
        self._remove_created()

    def _remove_created(self) -> None:
        if self._created is None:
            return
        folder = self.target.parent
        while True:
            try:
                folder.rmdir()  # only empty folders: never anything a user put there since
            except OSError:
                return
            if folder == self._created:
                return
            folder = folder.parent


def claim_folder(path: str | Path, kind: str) -> Path:
    """A folder that swarmpc may fill with files of ``kind`` (``bench``, ``reproduce``): a new or
    empty folder is created and marked ``.swarmpc-<kind>``; a folder with that marker is reused;
    anything else is refused, so a report never overwrites a user's file of the same name."""
    folder = normalise_target(path)
    marker = folder / f".swarmpc-{kind}"
    if os.path.islink(folder):
        raise OutputError(f"{folder}: is a symbolic link; choose a real folder for --out")
    if os.path.lexists(folder) and not _is_empty_folder(folder):
        if not (folder.is_dir() and marker.is_file() and not marker.is_symlink()):
            raise OutputError(f"{folder}: exists and is not a swarmpc {kind} folder; choose another --out")
        return folder
    try:
        folder.mkdir(parents=True, exist_ok=True)
        marker.write_text(json.dumps({"format": f"swarmpc-{kind}", "version": 1}) + "\n")
    except OSError as err:
        raise OutputError(f"{folder}: cannot write there ({err.strerror or err})") from None
    return folder


def unclaim_folder(folder: Path, kind: str) -> None:
    """Undo :func:`claim_folder` of a folder nothing was written to: its marker goes, then the
    folder if that left it empty (nothing else is ever removed)."""
    marker = f".swarmpc-{kind}"
    try:
        if os.listdir(folder) == [marker]:
            (folder / marker).unlink()
            folder.rmdir()
    except OSError:
        pass


def refuse_existing_file(path: Path, overwrite: bool) -> None:
    """An output file given by the user (``--out FILE``) may replace an existing file only with
    ``overwrite``, and never a folder or a link."""
    if not os.path.lexists(path):
        return
    if os.path.islink(path) or not path.is_file():
        raise OutputError(f"{path}: exists and is not a regular file; choose another --out")
    if not overwrite:
        raise OutputError(f"{path}: exists; --overwrite replaces it")
