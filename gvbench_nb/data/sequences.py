"""Sequences: an image root plus labelled pairs in GV-Bench's pair-file format, one pair a line:
``query_path reference_path label``. Paths are shell-quoted and normalised before the duplicate
and self-pair checks; loading pairs never touches the images (docs/reliability.md)."""

from __future__ import annotations

import os
import posixpath
import random
import shlex
from collections import Counter
from collections.abc import Iterable, Iterator
from collections.abc import Sequence as SequenceType
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import pandas as pd

from gvbench_nb import GVBenchError
from gvbench_nb.io_utils import atomic_write_text
from gvbench_nb.protocol.images import IMAGE_EXTENSIONS, path_problem


class PairFileError(GVBenchError, ValueError):
    """A pair file line is malformed, duplicated or points outside the image root."""


class MissingImagesError(PairFileError):
    """Images the pairs name are not under the image root."""


@dataclass(frozen=True)
class Pair:
    query: str
    reference: str
    label: int


MAX_PATH_CHARS = 4096  # PATH_MAX of Linux; longer names cannot be opened anyway
MAX_NAME_BYTES = 255  # NAME_MAX: the longest file or folder name most file systems take


def shorten(text: str, limit: int = 80) -> str:
    """``text`` cut to ``limit`` characters with how long it was (for error messages)."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def name_problem(name: str) -> str | None:
    """Why ``name`` (a sequence's or a method's: files and folders bear it) is not a plain file name, or None."""
    if not name or not name.strip():
        return "is empty"
    if any(mark in name for mark in ("/", "\\")):
        return "holds a path separator"
    if any(ord(char) < 32 or ord(char) == 127 for char in name):
        return "holds a control character (a NUL byte, a tab, a newline, ...)"
    if name.startswith("."):
        return "starts with '.' (names a hidden, current or parent folder)"
    if len(name.encode()) > MAX_NAME_BYTES:
        return f"is longer than {MAX_NAME_BYTES} bytes, which file systems do not allow in a name"
    return None


def _check_length(path_text: str, where: str) -> None:
    if "\0" in path_text:
        raise PairFileError(
            f"{where}: path {shorten(path_text)!r} holds a NUL byte, which no file name can; "
            "is this a text pair file? Fix the line"
        )
    if len(path_text) > MAX_PATH_CHARS:
        raise PairFileError(
            f"{where}: path {shorten(path_text)!r} is longer than {MAX_PATH_CHARS} characters; "
            "is this line a pair? Write 'query_path reference_path label'"
        )
    longest = max(path_text.replace("\\", "/").split("/"), key=lambda part: len(part.encode()))
    if len(longest.encode()) > MAX_NAME_BYTES:
        raise PairFileError(
            f"{where}: the name {shorten(longest)!r} in a path is longer than {MAX_NAME_BYTES} bytes, "
            "which file systems do not allow; fix the path"
        )


def _split_fields(line: str, where: str) -> list[str]:
    if '"' not in line and "'" not in line:
        return line.split()
    try:
        return shlex.split(line, comments=False, posix=True)
    except ValueError as error:  # an unclosed quote
        raise PairFileError(
            f"{where}: {error} in {shorten(line)!r}; close the quote around the path "
            '(paths with spaces are written "like this.jpg")'
        ) from None


def _check_relative(path_text: str, where: str) -> None:
    # Backslashes count as separators too: a list written on Windows must not escape
    # the root when it is read there ('..\\x', 'C:\\x', '\\\\server\\share').
    path = PurePosixPath(path_text.replace("\\", "/"))
    if path.is_absolute() or (len(path_text) > 1 and path_text[1] == ":"):
        raise PairFileError(f"{where}: absolute path {path_text!r}; paths must be relative to the image root")
    if ".." in path.parts:
        raise PairFileError(f"{where}: path {path_text!r} escapes the image root ('..'); paths must stay inside it")


def parse_pairs(lines: Iterable[str], source: str = "<pairs>") -> list[Pair]:
    """Parse pair-file lines (blank and ``#`` lines skipped), rejecting anything that is not
    exactly a valid pair; errors name the source and line and say what to do."""
    return check_pairs(_pair_fields(lines, source), source)


def _pair_fields(lines: Iterable[str], source: str) -> Iterator[tuple[int, str, str, str]]:
    for line_number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{source}:{line_number}"
        fields = _split_fields(line, where)
        if len(fields) != 3:
            hint = (
                '; write a path holding spaces in quotes, e.g. "day 1/a.jpg"'
                if len(fields) > 3 and fields[-1] in ("0", "1")
                else ""
            )
            raise PairFileError(
                f"{where}: expected 3 fields 'query_path reference_path label', got {len(fields)}: "
                f"{shorten(line)!r}{hint}"
            )
        yield line_number, fields[0], fields[1], fields[2]


def check_pairs(rows: Iterable[tuple[int, str, str, str]], source: str, unit: str = "line") -> list[Pair]:
    """The one check of a pair list, whichever door it came through (a pair file, imported scores): rows
    ``(number, query, reference, label text)``, a bad one refused naming ``source`` and ``unit`` (``file:line``,
    ``file: pair N``); returns the pairs with normalised paths, so a repeat in other spellings is caught."""
    pairs: list[Pair] = []
    seen: dict[tuple[str, str], tuple[int, int]] = {}  # (query, reference) -> (number, label)
    for number, query, reference, label_text in rows:
        where = f"{source}:{number}" if unit == "line" else f"{source}: {unit} {number}"
        if label_text not in ("0", "1"):
            raise PairFileError(f"{where}: label must be 0 or 1, got {shorten(label_text)!r}")
        for path_text in (query, reference):
            _check_length(path_text, where)
            _check_relative(path_text, where)
        # night/./a.jpg, night//a.jpg -> night/a.jpg: one spelling a file
        query, reference = posixpath.normpath(query), posixpath.normpath(reference)
        label = int(label_text)
        if query == reference:
            raise PairFileError(
                f"{where}: self-pair: query and reference are both {query}; "
                "a pair needs two different images, remove this line"
            )
        for key, order in (((query, reference), ""), ((reference, query), ", in the other order")):
            if key in seen:
                first, first_label = seen[key]
                labels = f", with the opposite label: {first_label} there, {label} here" if first_label != label else ""
                raise PairFileError(
                    f"{where}: duplicate pair {query} {reference} (first on {unit} {first}{order}{labels}); "
                    "remove one of them"
                )
        seen[(query, reference)] = (number, label)
        pairs.append(Pair(query, reference, label))
    return pairs


def read_text(path: Path, what: str) -> str:
    """A text file of lines (a pair file, a score table), refused naming file:line unless UTF-8;
    utf-8-sig drops the byte-order mark some Windows editors write."""
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line_number = data[: error.start].count(b"\n") + 1
        raise PairFileError(
            f"{path}:{line_number}: not UTF-8 text ({data[error.start : error.start + 4]!r}); "
            f"is this {what}? Save it as UTF-8 text"
        ) from None


def read_pairs(path: str | os.PathLike[str]) -> list[Pair]:
    path = Path(path)
    problem = path_problem(path)
    if problem is not None:
        what = {"does not exist": "not found", "is a folder, not a file": "is a folder, not a pair file"}.get(problem)
        raise PairFileError(
            (f"pair file {what}: {path}" if what else f"pair file {path} {problem}")
            + "; set the params' pairs to a file of "
            "'query_path reference_path label' lines (or a pairs_builder that makes it)"
        )
    # splitlines() and strip() make CRLF (and lone CR) line endings read like LF.
    pairs = parse_pairs(read_text(path, "a pair file").splitlines(), source=str(path))
    if not pairs:
        raise PairFileError(f"{path}: holds no pairs")
    return pairs


def pair_line_numbers(path: str | os.PathLike[str]) -> list[int]:
    """The line of each pair of a pair file, in order (for errors naming file:line)."""
    lines = Path(path).read_text(encoding="utf-8-sig").splitlines()
    return [n for n, line in enumerate(lines, start=1) if line.strip() and not line.strip().startswith("#")]


def format_pairs(pairs: Iterable[Pair]) -> str:
    """Pair-file text; a path holding spaces or quotes is written in quotes."""
    quote = lambda path: path if path and not any(c.isspace() or c in "'\"" for c in path) else shlex.quote(path)
    return "".join(f"{quote(p.query)} {quote(p.reference)} {int(p.label)}\n" for p in pairs)


def write_pairs(path: str | os.PathLike[str], pairs: Iterable[Pair | tuple[str, str, int]]) -> Path:
    """Write a GV-Bench pair file atomically (a crash leaves the old file or none)."""
    checked = [p if isinstance(p, Pair) else Pair(str(p[0]), str(p[1]), int(p[2])) for p in pairs]
    for pair in checked:
        if pair.label not in (0, 1):
            raise PairFileError(f"label must be 0 or 1, got {pair.label!r} for {pair}")
        if any(not part.strip() or "\n" in part or "\r" in part for part in (pair.query, pair.reference)):
            raise PairFileError(f"paths may not be empty or hold line breaks: {pair}")
    return atomic_write_text(Path(path), format_pairs(checked))


@dataclass
class Sequence:
    """A named benchmark sequence: labelled pairs over images under ``image_root``."""

    name: str
    image_root: Path
    pairs: list[Pair]
    # Where the pairs came from (pair file and its SHA-256, builder and options), for run.json.
    origin: dict[str, object] = field(default_factory=dict, compare=False)

    @property
    def images(self) -> list[str]:
        """Unique image paths (relative to the root), in first-seen order."""
        return list(dict.fromkeys(p for pair in self.pairs for p in (pair.query, pair.reference)))

    @property
    def queries(self) -> list[str]:
        return list(dict.fromkeys(pair.query for pair in self.pairs))

    def to_frame(self) -> pd.DataFrame:
        frame = pd.DataFrame(self.pairs, columns=["query", "reference", "label"])
        return frame.rename_axis("pair_index").reset_index()

    def limited(self, limit: int | None) -> Sequence:
        """The first ``limit`` pairs (the same prefix every time, so runs are comparable)."""
        if limit is None or limit >= len(self.pairs):
            return self
        if limit < 1:
            raise ValueError(f"limit must be a positive number of pairs, got {limit}")
        return Sequence(self.name, self.image_root, self.pairs[:limit], {**self.origin, "limit": limit})

    def check_images(self) -> None:
        """Raise ``MissingImagesError`` when an image of the pairs is not a readable file, naming
        how many, the first, what it is (missing, a broken link, a folder...) and its pair."""
        if not Path(self.image_root).is_dir():
            raise MissingImagesError(
                f"image_root {self.image_root} of sequence {self.name!r} does not exist or is not a folder; "
                "set image_root (or --image-root) to the folder the pair file's paths are relative to"
            )
        found = ((name, path_problem(self.image_root / name)) for name in self.images)
        problems = {name: problem for name, problem in found if problem is not None}
        if problems:
            first, problem = next(iter(problems.items()))
            index, pair = next((i, p) for i, p in enumerate(self.pairs) if first in (p.query, p.reference))
            missing = all(p == "does not exist" for p in problems.values())
            state = "are missing" if missing else "cannot be read"
            what = "" if problem == "does not exist" else f", which {problem}"
            raise MissingImagesError(
                f"{len(problems)} of {len(self.images)} images of sequence {self.name!r} {state} under "
                f"{self.image_root}, first {first}{what} (pair {index}: {pair.query} {pair.reference}"
                f"{', ' + str(self.origin['pairs_file']) if self.origin.get('pairs_file') else ''}); "
                "restore them, or remove the pairs that use them"
            )


def summarize(sequence: Sequence) -> dict[str, object]:
    """Counts a user checks first: pairs, queries, images, positives, positives a query."""
    positives_per_query = Counter(p.query for p in sequence.pairs if p.label == 1)
    candidates_per_query = Counter(p.query for p in sequence.pairs)
    queries = sequence.queries
    n_positives = sum(p.label for p in sequence.pairs)
    return {
        "sequence": sequence.name,
        "n_pairs": len(sequence.pairs),
        "n_positives": n_positives,
        "n_negatives": len(sequence.pairs) - n_positives,
        "n_queries": len(queries),
        "n_images": len(sequence.images),
        "candidates_per_query": len(sequence.pairs) / max(len(queries), 1),
        "positives_per_query": n_positives / max(len(queries), 1),
        "queries_without_positive": sum(1 for q in queries if positives_per_query[q] == 0),
        "max_candidates_per_query": max(candidates_per_query.values()) if queries else 0,
    }


def folder_images(image_root: str | os.PathLike[str], folder: str) -> list[str]:
    """The images of ``image_root/folder``, named ``folder/file`` (relative to the root), sorted."""
    paths = (Path(image_root) / folder).iterdir()
    return sorted(f"{folder}/{p.name}" for p in paths if p.suffix.lower() in IMAGE_EXTENSIONS)


def frame_index(name: str) -> int:
    """Frame number from a name such as ``night_right/Image042.jpg`` -> 42."""
    stem = PurePosixPath(name).stem
    digits = "".join(ch for ch in stem if ch.isdigit())
    if not digits:
        raise ValueError(f"no frame number in {name!r}")
    return int(digits)


def frame_tolerance_pairs(
    query_names: SequenceType[str],
    reference_names: SequenceType[str],
    tolerance: int = 2,
    candidates_per_query: int = 10,
    near_negatives: int = 2,
    near_window: int = 8,
    seed: int = 0,
    negative_margin: int | None = None,
) -> list[Pair]:
    """Rule-built candidates of a frame-aligned sequence: references with |i - j| <= tolerance
    (true), seeded near negatives (low <= |i - j| <= near_window), then far ones (> 4 * near_window);
    ``negative_margin`` raises ``low`` to leave out views too close to call."""
    low = tolerance + 1 if negative_margin is None else negative_margin
    if negative_margin is not None and negative_margin <= tolerance:
        raise ValueError(
            f"negative_margin {negative_margin} must exceed tolerance {tolerance} "
            "(a negative cannot be as close as a true neighbour); raise it or drop it"
        )
    if near_negatives and near_window < low:
        raise ValueError(
            f"near_window {near_window} is below the smallest negative gap {low}: "
            f"no near negative can be drawn; set near_window to at least {low}"
        )
    rng = random.Random(seed)
    references = {frame_index(r): r for r in reference_names}
    frames = sorted(references)
    pairs: list[Pair] = []
    for query in query_names:
        i = frame_index(query)
        positives = [j for j in frames if abs(i - j) <= tolerance]
        near = [j for j in frames if low <= abs(i - j) <= near_window]
        far = [j for j in frames if abs(i - j) > 4 * near_window]
        chosen_near = rng.sample(near, min(near_negatives, len(near)))
        n_far = max(candidates_per_query - len(positives) - len(chosen_near), 0)
        chosen_far = rng.sample(far, min(n_far, len(far)))
        pairs += [Pair(query, references[j], 1) for j in positives]
        pairs += [Pair(query, references[j], 0) for j in chosen_near + chosen_far]
    return pairs
