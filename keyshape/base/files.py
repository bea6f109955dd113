"""Safe outputs, and the one output rule every command follows (``docs/reliability.md``).

Design notes and figures: docs/reliability.md, "Notes on the code", ``keyshape/base/files.py``.
"""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import posixpath
import re
import secrets
import shutil
import tempfile
import threading
from pathlib import Path
from typing import IO, Iterable, Iterator

from keyshape.base.errors import InputError, require_file

#: file recording, in a folder output, the files keyshape wrote there (relative paths)
MANIFEST = ".keyshape-outputs.json"
#: the record's kind for single-file outputs (every command's ``-o FILE``, sidecars included)
FILES_KIND = "files"


def _umask_mode(base: int = 0o666) -> int:
    mask = os.umask(0)
    os.umask(mask)
    return base & ~mask


def _tmp_sibling(path: Path, suffix: str = "") -> Path:
    """A new empty temporary file beside ``path`` with the permissions a plain ``open`` would give.

    ``mkstemp`` creates files readable by their owner only; outputs that users
    share (videos, .glb) must get the usual umask-derived mode instead.
    """
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.{run_token()}-", suffix=".partial" + suffix, dir=path.parent)
    os.close(fd)
    os.chmod(name, _umask_mode())
    return Path(name)


_TOKEN = os.environ.get("KEYSHAPE_RUN_TOKEN") or secrets.token_hex(4)


def run_token() -> str:
    """This run's token, part of every hidden temporary file's name (``.NAME.ks<token>-XXXX.partial``):
    a cleanup deletes only temporaries carrying its own run's token, never a user's file that merely
    looks like one. ``keyshape batch`` sets ``KEYSHAPE_RUN_TOKEN`` so that its workers share it."""
    return "ks" + (os.environ.get("KEYSHAPE_RUN_TOKEN") or _TOKEN)


class Run:
    """The output rule's view of one command run: its declared inputs and whether ``--overwrite`` was given.

    While a run is active (:func:`run_rules`, which ``keyshape.cli.main`` enters for every command),
    every file written through :func:`atomic_path` / :func:`atomic_write` is checked by
    :func:`guard_file` just before it is created and again before it replaces anything, and is
    then recorded with its SHA-256 in its folder's :data:`MANIFEST`.
    """

    def __init__(self, inputs: Iterable[str | Path | None] = (), overwrite: bool = False,
                 can_overwrite: bool = False, command: str = "keyshape"):
        self.inputs = [Path(i) for i in inputs if i is not None and str(i) != ""]
        self.overwrite = bool(overwrite)
        self.can_overwrite = bool(can_overwrite)
        self.command = command


_RUN: Run | None = None


@contextlib.contextmanager
def run_rules(run: Run) -> Iterator[Run]:
    """Apply the output rule to every file written while the block runs (see :class:`Run`)."""
    global _RUN
    old, _RUN = _RUN, run
    try:
        yield run
    finally:
        _RUN = old


def _run_default(overwrite: bool | None, inputs: Iterable[str | Path | None] | None) -> tuple[bool, list]:
    """``overwrite`` and ``inputs`` as given, else (None) the active run's ``--overwrite`` and declared inputs
    (False and none in library use, where no run is active)."""
    if overwrite is None:
        overwrite = _RUN is not None and _RUN.overwrite
    if inputs is None:
        inputs = _RUN.inputs if _RUN is not None else ()
    return bool(overwrite), [i for i in inputs if i is not None]


def _in_temp_folder(path: Path) -> bool:
    """True inside a folder output's hidden temporary folder (checked and recorded when moved in)."""
    return any(_is_hidden_temp(part) for part in Path(os.path.abspath(path)).parts[:-1])


_USER_SAVE = threading.local()


@contextlib.contextmanager
def user_save() -> Iterator[None]:
    """Writes in this block (this thread only) are the user's own saves from a web page (pose-edit's
    POSES.json, label's ``.pts``): the user asked for exactly that file to change, so the output rule
    does not apply to them (they are still atomic)."""
    old = getattr(_USER_SAVE, "on", False)
    _USER_SAVE.on = True
    try:
        yield
    finally:
        _USER_SAVE.on = old


@contextlib.contextmanager
def keyshape_store() -> Iterator[None]:
    """Writes in this block (this thread only) go to keyshape's own store (the rig cache under
    ``~/.cache/keyshape``), not to an output the user named: the output rule does not apply."""
    with user_save():
        yield


_OUR_TEMP = re.compile(r"^\..+\.ks[0-9a-f]+-[^.]+\.partial(\.[^.]+)?$")


def _ruled(path: Path) -> bool:
    return (_RUN is not None and not getattr(_USER_SAVE, "on", False) and not _in_temp_folder(path)
            and path.name != MANIFEST and not _OUR_TEMP.match(path.name))


def _same_file(a: Path, b: Path) -> bool:
    """Same file: same device and inode (hard links, symlinks, ``..``, ``.``) or the same resolved path."""
    try:
        sa, sb = os.stat(a), os.stat(b)
        if (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino):
            return True
    except OSError:
        pass
    return _real(a) == _real(b)


def recorded_sha(path: str | Path) -> str | None:
    """The SHA-256 keyshape's record (its folder's :data:`MANIFEST`) holds for ``path``, or None
    (no record, a record keyshape did not write, or no hash for this file)."""
    path = Path(path)
    try:
        record = _read_manifest(path.parent)
    except InputError:
        return None
    return None if record is None else record.sha.get(path.name)


def written_by_keyshape(path: str | Path) -> bool:
    """True when ``path`` is a plain file (not a link) whose content has exactly the SHA-256 that
    keyshape's record in its folder holds for it: the record is a claim, verified here."""
    path = Path(path)
    if path.is_symlink() or not path.is_file():
        return False
    want = recorded_sha(path)
    try:
        return want is not None and sha256_file(path) == want
    except OSError:
        return False


def guard_file(path: str | Path, what: str = "output") -> Path:
    """The output rule for one file output of the active run (a no-op without one).

    Refused (:class:`InputError` naming ``path``): a symbolic link (never written through or
    replaced); a path that is one of the run's inputs (same device and inode, or the same resolved
    path); an existing file that keyshape's record does not show it wrote with exactly this content,
    unless the run was given ``--overwrite``.
    """
    path = Path(path)
    run = _RUN
    if run is None or getattr(_USER_SAVE, "on", False):
        return path
    if path.name == MANIFEST:
        raise InputError(f"{MANIFEST} is the name of keyshape's own record; choose another name", path)
    if path.is_symlink():
        raise InputError("is a symbolic link; keyshape never writes through or replaces a link: "
                         "choose another name", path)
    for inp in run.inputs:
        if (path.exists() or inp.exists()) and _same_file(path, inp):
            raise InputError(f"the {what} is one of the inputs ({inp}); choose another name", path)
    if path.exists() and not path.is_dir() and not run.overwrite and not written_by_keyshape(path):
        why = ("was changed since keyshape wrote it" if recorded_sha(path) is not None
               else "was not written by keyshape")
        hint = ", or pass --overwrite" if run.can_overwrite else ""
        raise InputError(f"exists and {why}; keyshape replaces only files its record ({MANIFEST}) shows it "
                         f"wrote with this content: choose another name, move it away{hint}", path)
    return path


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """An exclusive lock on ``folder`` while its record is read and rewritten (parallel writers)."""
    try:
        import fcntl
        fd = os.open(folder, os.O_RDONLY)
    except (ImportError, OSError):
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _write_record(folder: Path, kinds: dict[str, Iterable[str]], sha: dict[str, str]) -> None:
    kinds = {k: sorted(v) for k, v in sorted(kinds.items()) if v}
    listed = {f for v in kinds.values() for f in v}
    text = json.dumps({"written_by": "keyshape", "version": 3, "outputs": kinds,
                       "sha256": {k: v for k, v in sorted(sha.items()) if k in listed}}, indent=0)
    with contextlib.suppress(OSError):
        if (folder / MANIFEST).read_text() == text:     # unchanged: a rerun that rewrote nothing leaves it be
            return
    with atomic_write(folder / MANIFEST) as f:
        f.write(text)


def _remember(path: Path, digest: str) -> None:
    """Record in ``path``'s folder that keyshape wrote ``path`` with content hash ``digest``
    (kind :data:`FILES_KIND`). A record keyshape did not write is left alone (nothing recorded)."""
    folder = path.parent
    with _locked(folder):
        try:
            record = _read_manifest(folder) or _Record()
        except InputError:
            return
        name = path.name
        kinds = {k: set(v) - {name} for k, v in record.items()}
        kinds.setdefault(FILES_KIND, set()).add(name)
        sha = dict(record.sha)
        sha[name] = digest
        with contextlib.suppress(OSError):
            _write_record(folder, kinds, sha)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path with ``path``'s suffix for a writer that takes a file name.

    For writers such as ``cv2.VideoWriter`` or ``np.savez`` that open the file
    themselves. The temporary file is renamed over ``path`` when the block
    exits without error and removed otherwise.
    """
    path = Path(path)
    ruled = _ruled(path)
    if ruled:
        guard_file(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = _tmp_sibling(path, suffix=path.suffix)
    except OSError as exc:
        raise _about(exc, path, None) from None
    try:
        yield tmp
        if ruled:
            guard_file(path)
            digest = sha256_file(tmp)
        os.replace(tmp, path)
        if ruled:
            _remember(path, digest)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            new = _about(exc, path, tmp)
            if new is not exc:
                raise new from None
        raise


#: errors of writing a file whatever its name: reported as the output's, not the temporary file's
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS}


def _about(exc: OSError, path: Path, tmp: Path | None) -> OSError:
    """``exc`` re-aimed at the user's ``path`` when it concerns keyshape's hidden temporary file
    (or names no file and is a disk-full or read-only error), so messages name what the user gave."""
    if exc.filename is None:
        ours = exc.errno in _WRITE_ERRNOS
    else:
        names = {Path(str(exc.filename)), Path(str(exc.filename2))} if exc.filename2 else {Path(str(exc.filename))}
        ours = (tmp is not None and tmp in names) or \
            any(n.parent == path.parent and n.name.startswith(f".{path.name}.") for n in names)
    return OSError(exc.errno, exc.strerror or str(exc), str(path)) if ours else exc


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", **open_kwargs) -> Iterator[IO]:
    """Open a temporary sibling of ``path`` for writing; rename it over ``path`` on success.

    On any exception the temporary file is removed and ``path`` is untouched.

    Examples
    --------
    >>> with atomic_write("out.csv") as f:  # doctest: +SKIP
    ...     f.write("a,b\\n")
    """
    with atomic_path(path) as tmp:
        with open(tmp, mode, **open_kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and not p.is_symlink() and p != p.parent:
        p = p.parent
    return p


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output(path: str | Path, kind: str = "file", inputs: Iterable[str | Path | None] = (),
                 what: str = "output") -> Path:
    """Check that ``path`` can be written as a ``kind`` ("file" or "folder") output; return it.

    Raises :class:`InputError` naming the path when a parent is a file or not
    writable, when a file output is an existing folder (or a folder output an
    existing file), or when the output is one of ``inputs`` (or, for a folder,
    holds an input under a name keyshape would write: see :func:`atomic_dir`).
    Nothing is created.
    """
    path = Path(path)
    if str(path) == "":
        raise InputError(f"empty {what} path")
    if kind == "file":
        if path.is_dir():
            raise InputError(f"is a folder; the {what} must be a file name", path)
        if path.name in ("", ".", ".."):
            raise InputError(f"not a file name; the {what} must be a file name", path)
    elif path.exists() and not path.is_dir():
        raise InputError(f"exists and is not a folder; the {what} must be a folder", path)
    anc = _nearest_existing(path.parent if kind == "file" or not path.exists() else path)
    if not anc.is_dir():
        raise InputError(f"{anc} is not a folder, so {what} {path} cannot be written", path)
    if not os.access(anc, os.W_OK | os.X_OK):
        raise InputError(f"folder {anc} is not writable", path)
    if kind == "file" and path.exists() and not os.access(path, os.W_OK) and not os.access(path.parent, os.W_OK):
        raise InputError("not writable", path)
    if kind == "file":
        try:
            name_max = os.pathconf(anc, "PC_NAME_MAX")
        except (OSError, ValueError):
            name_max = 255
        # the hidden temporary sibling adds about 20 characters to the name
        if len(os.fsencode(path.name)) + 20 > name_max:
            raise InputError(f"file name too long ({len(os.fsencode(path.name))} bytes; at most "
                             f"{name_max - 20} here)", path)
        guard_file(path, what)
    elif _RUN is not None and path.is_symlink():
        raise InputError(f"is a symbolic link; keyshape never writes through a link: choose another {what} folder",
                         path)
    for inp in (Path(i) for i in inputs if i is not None):
        if kind == "file" and _same(path, inp):
            raise InputError(f"the {what} is one of the inputs ({inp}); choose another name", path)
        if kind == "folder" and path.is_dir() and inp.exists() and _same(path, inp):
            raise InputError(f"the {what} folder is an input folder ({inp}); choose another folder", path)
    return path


def check_outputs(files: Iterable[str | Path | None] = (), folders: Iterable[str | Path | None] = (),
                  inputs: Iterable[str | Path | None] = ()) -> None:
    """:func:`check_output` for every file and folder output (None entries skipped), and refuse
    one path given twice as an output."""
    inputs = [i for i in inputs if i is not None]
    seen: dict[str, Path] = {}
    for kind, paths in (("file", files), ("folder", folders)):
        for p in (p for p in paths if p is not None):
            check_output(p, kind, inputs)
            key = os.path.abspath(p)
            if key in seen:
                raise InputError("named twice as an output", p)
            seen[key] = Path(p)


_LEGACY = "legacy"      # the kind of files an older keyshape recorded without naming its command


def _manifest_error(folder: Path, why: str) -> InputError:
    return InputError(f"keyshape's ownership record {MANIFEST} {why}; it is not trusted as a list of "
                      "files to replace: remove it or choose another folder", folder)


def _valid_entry(entry, folder: Path) -> str:
    """One recorded file name, checked as untrusted: a plain relative path inside the folder."""
    if not isinstance(entry, str) or not entry:
        raise _manifest_error(folder, f"lists {entry!r}, which is not a file name")
    if ("\\" in entry or "\x00" in entry or entry.startswith("/") or (len(entry) > 1 and entry[1] == ":")
            or entry.strip() != entry):
        raise _manifest_error(folder, f"lists {entry!r}, which is not a relative path inside the folder")
    parts = entry.split("/")
    if any(part in ("", ".", "..") for part in parts) or posixpath.normpath(entry) != entry:
        raise _manifest_error(folder, f"lists {entry!r}, which is not a normalised path inside the folder")
    if entry == MANIFEST or _is_hidden_temp(parts[0]):
        raise _manifest_error(folder, f"lists {entry!r}, a name keyshape never records")
    return entry


class _Record(dict):
    """Command kind -> the files that kind wrote (a dict), with ``sha`` : file -> SHA-256 as recorded."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.sha: dict[str, str] = {}


_HEX64 = frozenset("0123456789abcdef")


def _read_manifest(folder: Path) -> _Record | None:
    """The ownership record of ``folder``: command kind -> the files that kind wrote there.

    None when there is none. The record is untrusted input: anything but a JSON object written
    by keyshape whose entries are normalised relative paths inside the folder (no absolute path,
    no ``..``) is a one-line :class:`InputError`, never a list of files to replace or delete.
    A record of an older keyshape (one flat ``files`` list) is read as kind ``"legacy"``: its
    files may be replaced by name but are never pruned.
    """
    m = folder / MANIFEST
    if not m.exists() and not m.is_symlink():
        return None
    if m.is_symlink() or not m.is_file():
        raise _manifest_error(folder, "is not a plain file")
    try:
        data = json.loads(m.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        raise _manifest_error(folder, "is unreadable") from None
    except RecursionError:
        raise _manifest_error(folder, "is nested too deeply") from None
    if not isinstance(data, dict) or data.get("written_by") != "keyshape":
        raise _manifest_error(folder, "was not written by keyshape")
    record = _Record()
    if "outputs" in data:
        outs = data["outputs"]
        if not isinstance(outs, dict):
            raise _manifest_error(folder, "has an 'outputs' that is not an object")
        for kind, files in outs.items():
            if not kind or not isinstance(files, list):
                raise _manifest_error(folder, f"has a bad entry for {kind!r}")
            record[kind] = {_valid_entry(e, folder) for e in files}
    elif isinstance(data.get("files"), list):
        record[_LEGACY] = {_valid_entry(e, folder) for e in data["files"]}
    else:
        raise _manifest_error(folder, "has no list of files")
    sha = data.get("sha256", {})
    if not isinstance(sha, dict):
        raise _manifest_error(folder, "has a 'sha256' that is not an object")
    for entry, digest in sha.items():
        if not (isinstance(digest, str) and len(digest) == 64 and set(digest) <= _HEX64):
            raise _manifest_error(folder, f"has a bad content hash for {entry!r}")
        record.sha[_valid_entry(entry, folder)] = digest
    return record


def _is_hidden_temp(name: str) -> bool:
    return name.startswith(".keyshape-") and name.endswith(".partial")


def _real(p: str | Path) -> str:
    return os.path.normcase(os.path.realpath(p))


def _inside(child: str, parent: str) -> bool:
    return child == parent or child.startswith(parent.rstrip(os.sep) + os.sep)


class InputSet:
    """A run's inputs, resolved: a path touches them when it is one of them (a hard link of one
    included) or lies inside an input folder (links resolved).

    ``output``: the run's output folder. An input folder that holds the output folder (``-o
    targets/frames``) covers only what lies outside the output folder: inside it, only the
    inputs themselves are protected (a command lists the files it reads, e.g. every target).
    """

    def __init__(self, inputs: Iterable[str | Path | None], output: str | Path | None = None):
        self.items = []
        out = _real(output) if output is not None else None
        for p in (Path(i) for i in inputs if i is not None and str(i) != ""):
            if p.exists():
                real = _real(p)
                self.items.append((p, real, p.is_dir(), out if out is not None and p.is_dir() and
                                   out != real and _inside(out, real) else None))

    def touched_by(self, path: Path) -> Path | None:
        """The input that writing or deleting ``path`` would touch, or None."""
        r = _real(path)
        for p, real, is_dir, carved in self.items:
            if r == real or (is_dir and _inside(r, real) and not (carved and _inside(r, carved))):
                return p
            with contextlib.suppress(OSError):
                if path.exists() and os.path.samefile(path, p):     # a hard link of an input
                    return p
        return None


def _link_on_the_way(root: Path, rel: str) -> Path | None:
    """The first folder between ``root`` and ``root/rel`` (both excluded) that is a symbolic link."""
    p = root
    for part in rel.split("/")[:-1]:
        p = p / part
        if p.is_symlink():
            return p
    return None


def check_output_dir(path: str | Path, overwrite: bool | None = None,
                     inputs: Iterable[str | Path | None] | None = None) -> Path:
    """Check a folder output before any computation: :func:`check_output` (not an input folder);
    its ownership record (:data:`MANIFEST`), if any, is valid; and a
    non-empty folder that keyshape did not make (no record) is refused unless ``overwrite``
    (``overwrite``, ``inputs``: None, the running command's ``--overwrite`` and declared inputs)."""
    overwrite, inputs = _run_default(overwrite, inputs)
    path = check_output(path, "folder", inputs)
    record = _read_manifest(path) if path.is_dir() else None
    if path.is_dir() and not overwrite and not (record and set(record) - {FILES_KIND}):
        others = [p.name for p in path.iterdir() if not _is_hidden_temp(p.name)]
        if others:
            raise InputError(f"folder is not empty and was not made by keyshape ({len(others)} entries, e.g. "
                             f"{sorted(others)[0]!r}); choose an empty or new folder, or pass --overwrite "
                             "(only the files keyshape writes are replaced, nothing is deleted)", path)
    return path


def _rel_files(root: Path) -> list[str]:
    """Files under ``root`` (relative POSIX paths), without its own manifest (a nested run's stays)."""
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*")
                  if (p.is_file() or p.is_symlink()) and p != root / MANIFEST)


@contextlib.contextmanager
def atomic_dir(path: str | Path, overwrite: bool | None = None, inputs: Iterable[str | Path | None] | None = None,
               kind: str = "output") -> Iterator[Path]:
    """Yield a hidden temporary folder whose files are moved into the folder ``path`` on success.

    The ownership rule, exactly as docs/reliability.md ("Folder outputs") states it: the folder's
    :data:`MANIFEST` records, per command ``kind`` (``"retarget"``, ``"demo"``, ...), the files that kind
    wrote with their content hashes; a run replaces and prunes only its own kind's earlier files, unchanged
    (or replaces with ``overwrite``), never an input, a file inside an input folder (:class:`InputSet`) or
    anything through a symbolic link, and rewrites the record. Every check is made before the first file
    moves; ``overwrite`` and ``inputs`` left None are the running command's (:class:`Run`). On error or
    interruption the temporary folder is removed and ``path`` is as it was.
    """
    if not kind:
        raise ValueError("atomic_dir needs a command kind")
    overwrite, inputs = _run_default(overwrite, inputs)
    path = check_output_dir(path, overwrite, inputs)
    guard = InputSet(inputs, output=path)
    created = not path.exists()
    path.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".keyshape-", suffix=".partial", dir=path))
    os.chmod(path if created else tmp, _umask_mode(0o777))
    os.chmod(tmp, _umask_mode(0o777))
    try:
        yield tmp
        new = _rel_files(tmp)
        new_sha = {rel: sha256_file(tmp / rel) for rel in new if not (tmp / rel).is_symlink()}
        with _locked(path):
            record = _read_manifest(path) or _Record()
            own = record.get(kind, set())

            def verified(rel: str) -> bool:
                """The record's claim checked: a plain file whose content has the recorded hash."""
                p = path / rel
                if rel not in record.sha or _link_on_the_way(path, rel) is not None or p.is_symlink() \
                        or not p.is_file():
                    return False
                try:
                    return sha256_file(p) == record.sha[rel]
                except OSError:
                    return False

            for rel in new:
                dest = path / rel
                link = _link_on_the_way(path, rel)
                if link is not None:
                    raise InputError(f"{link} is a symbolic link; keyshape does not write through links: "
                                     "move it away or choose another folder", dest)
                inp = guard.touched_by(dest)
                if inp is not None:
                    raise InputError(f"this run would overwrite its input {inp}; choose another folder", dest)
                if dest.is_symlink():
                    raise InputError("is a symbolic link; keyshape never writes through or replaces a link: "
                                     "move it away or choose another folder", dest)
                if dest.is_dir():
                    raise InputError("is a folder where keyshape writes a file; move it away", dest)
                if dest.exists() and not overwrite and not (rel in own and verified(rel)):
                    owner = next((k for k, v in record.items() if rel in v), None)
                    if owner == kind:
                        who = "by keyshape but has been changed since (its content is not the one recorded)"
                    elif owner:
                        who = f"by keyshape {owner}"
                    else:
                        who = "not by keyshape"
                    raise InputError(f"exists and was written {who}; keyshape {kind} replaces only its own "
                                     "earlier files, unchanged: choose another folder, or pass --overwrite", dest)
            prune = [rel for rel in sorted(own - set(new))
                     if verified(rel) and guard.touched_by(path / rel) is None]
            for rel in new:
                dest = path / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.replace(tmp / rel, dest)
            for rel in prune:
                stale = path / rel
                stale.unlink()
                parent = stale.parent
                while parent != path and not parent.is_symlink() and parent.is_dir() and not any(parent.iterdir()):
                    parent.rmdir()
                    parent = parent.parent
            taken = set(new)
            kinds = {k: {f for f in v - taken if os.path.lexists(path / f)} for k, v in record.items() if k != kind}
            kinds[kind] = set(new)
            sha = {k: v for k, v in record.sha.items() if k not in taken}
            sha.update(new_sha)
            _write_record(path, kinds, sha)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if created:
            with contextlib.suppress(OSError):
                path.rmdir()
        raise
    shutil.rmtree(tmp, ignore_errors=True)


def may_delete(path: str | Path) -> bool:
    """Whether keyshape may delete ``path``: never a symbolic link; under a command (:func:`run_rules`)
    only a file its record shows it wrote with exactly this content (:func:`written_by_keyshape`)."""
    path = Path(path)
    if path.is_symlink() or not path.is_file():
        return False
    return _RUN is None or written_by_keyshape(path)


def commit(tmp: str | Path, path: str | Path) -> None:
    """Rename the complete temporary file ``tmp`` (from :func:`_tmp_sibling`) over ``path`` under the
    output rule (:func:`guard_file`), and record it: for writers that keep their temporary open while
    they work (``keyshape track``'s streamed CSV and overlay)."""
    path, tmp = Path(path), Path(tmp)
    ruled = _ruled(path)
    if ruled:
        guard_file(path)
        digest = sha256_file(tmp)
    try:
        os.replace(tmp, path)
    except OSError as exc:
        raise _about(exc, path, tmp) from None
    if ruled:
        _remember(path, digest)


def partial_name(path: str | Path) -> Path:
    """Where an interrupted run puts its partial result: ``NAME.partial.SUFFIX`` beside ``path``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.partial{path.suffix}")


def found_beside(name: str | Path, folder: Path) -> Path | None:
    """The file ``name`` as given, else the file of its name in ``folder`` (a record naming a file that moved
    with it), else None."""
    return next((p for p in (Path(name), Path(folder) / Path(name).name) if p.is_file()), None)


def describe_os_error(exc: OSError) -> str:
    """One line for an :class:`OSError`: the file and what went wrong (disk full, read-only, ...)."""
    name = exc.filename
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOSPC:
        reason = "no space left on the device (disk full); nothing was replaced"
    elif exc.errno in (errno.EROFS,):
        reason = "read-only file system"
    if name is None:
        return reason
    extra = f" -> {exc.filename2}" if exc.filename2 else ""
    return f"{name}{extra}: {reason}"


def _json_number(text: str) -> float:
    v = float(text)
    if v != v or v in (float("inf"), float("-inf")):
        raise ValueError(f"number {text} is out of range")
    return v


def _json_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks (memory does not grow with the file)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_json(path: str | Path, what: str = "JSON file"):
    """Parse the JSON file ``path``; a missing file, bad JSON, ``NaN``/``Infinity`` or a number
    beyond the float range (``1e999``) is a one-line error naming it."""
    path = require_file(path, what)
    try:
        return json.loads(path.read_text(), parse_float=_json_number, parse_constant=_json_constant)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None
    except ValueError as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None
    except RecursionError:
        raise InputError("not valid JSON (nested too deeply)", path) from None


def write_json(path: str | Path, data, indent: int | None = 1, end: str = "", sort_keys: bool = False) -> None:
    """Write ``data`` as JSON (``indent`` 1, or compact with ``None``; then ``end``, e.g. a newline) atomically."""
    with atomic_write(path) as f:
        json.dump(data, f, indent=indent, sort_keys=sort_keys)
        f.write(end)
