"""The README and docs/*.md name only code that exists.

Documentation names code in four ways, and each is checked against the checkout:

* **file paths** in backticks or in fenced shell blocks — ``drivers/fifo.py``,
  ``ahrs_service/estimators/tuned/NAME.json`` (a word in capitals such as ``NAME`` is a
  placeholder and matches any name) — must exist: from the repository root, from
  ``ahrs_service/`` (the docs write ``estimators/…`` for ``ahrs_service/estimators/…``), or as
  the end of some file's path (``mavlink/attitude.py``). A bare ``name.py`` must exist somewhere;
* **dotted module paths** ``ahrs_service.x.y`` in backticks or code blocks must import, or name
  an attribute of a module that imports, and must not be an old path that moved (those still
  import behind a DeprecationWarning, ``ahrs_service/_moved.py``, but the docs name the new one);
* **commands** ``ahrs-service COMMAND [SUBCOMMAND] [--option …]`` must be accepted by the
  command line's own parser (``ahrs_service.cli.build_parser``): the command, the subcommand
  where the command has them, and every ``--option``;
* **links** ``[text](target)`` to files of the checkout must point at something that exists
  (web addresses and ``#anchors`` are not checked).

What is deliberately not checked: other projects' names (ArduPilot and PX4 parameters,
``src/lib/timesync``), paths outside the checkout (``../shared/…``, ``/dev/…``, ``/etc/…``),
files a command writes (``flight-logs/…``, ``results/…``, ``layout.json``) and shell commands that
are not ours. The last test feeds the checker a made-up page to show that it does fail.
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib
import importlib.util
import re
import warnings
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: the folders a path in the docs may start from (besides the repository root)
PATH_BASES = [ROOT, ROOT / "ahrs_service"]
#: file endings that name code or docs of this project; other endings (.mcap, .csv, .toml
#: examples) are files a user or a command makes
CODE_SUFFIXES = (".py", ".md", ".json", ".service", ".sh", ".txt", ".png", ".pyi")
#: path starts that are not in the checkout: outside it, or written by the commands
FOREIGN_PREFIXES = ("../", "/", "~", "./flight-logs", "flight-logs/", "results/", "replayed/",
                    "src/lib/", "http:", "https:", "github.com/", "$")
#: folders skipped when looking for a file by name
SKIP_DIRS = {".venv", ".git", "__pycache__", "node_modules", ".ci_cache", "build", "dist"}
#: other projects' files the docs name when they explain what was followed (MAVProxy's)
FOREIGN_FILES = {"mavproxy.py", "mavproxy_link.py"}

CODE_SPAN = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")
FENCE = re.compile(r"^```([\w-]*)\n(.*?)^```", re.S | re.M)
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
MODULE_PATH = re.compile(r"\bahrs_service(?:\.[A-Za-z_]\w*)+")
PATH_TOKEN = re.compile(r"^[\w.*<>-]*(?:/[\w.*<>-]*)*$")
PLACEHOLDER = re.compile(r"\b[A-Z][A-Z0-9_]{2,}\b")
SHELL_STOPS = {"&&", "||", "|", ";", ">", ">>", "2>", "#"}


# --------------------------------------------------------------------------- reading a page
def code_spans(text: str) -> list[str]:
    """Inline code (`like this`) outside fenced blocks."""
    outside = FENCE.sub("", text)
    return CODE_SPAN.findall(outside)


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced block."""
    return FENCE.findall(text)


def links(text: str) -> list[str]:
    return LINK.findall(FENCE.sub("", text))


# --------------------------------------------------------------------------- files
@lru_cache(maxsize=None)
def all_files() -> tuple[str, ...]:
    """Every file and folder of the checkout, as paths relative to the root with '/'."""
    found = []
    stack = [ROOT]
    while stack:
        folder = stack.pop()
        for entry in folder.iterdir():
            if entry.name in SKIP_DIRS or entry.name.endswith(".egg-info"):
                continue
            rel = entry.relative_to(ROOT).as_posix()
            if entry.is_dir():
                found.append(rel + "/")
                stack.append(entry)
            else:
                found.append(rel)
    return tuple(found)


@lru_cache(maxsize=None)
def our_folder_names() -> frozenset[str]:
    """The names of every folder of the checkout (``drivers``, ``estimators``, ``sample_clock`` …)."""
    return frozenset(f.rstrip("/").rsplit("/", 1)[-1] for f in all_files() if f.endswith("/"))


def looks_like_our_path(token: str) -> bool:
    """Whether a code span is a path into this project that should exist: a file with a code
    ending (a bare name only for ``.py``), or a folder; a path with a ``/`` only when its first
    folder is a folder name of ours (``bosch/bmi088/`` is PX4's, ``drivers/…`` ours)."""
    if not token or " " in token or "<" in token or token.startswith(FOREIGN_PREFIXES):
        return False
    if not PATH_TOKEN.match(token) or token in FOREIGN_FILES:
        return False
    if "/" in token.rstrip("/"):
        first = token.removeprefix("./").split("/", 1)[0]
        if first not in our_folder_names() and not (ROOT / first).exists():
            return False
    if token.endswith("/"):
        return token.rstrip("/").rsplit("/", 1)[-1] in our_folder_names() or "/" in token.rstrip("/")
    if not token.endswith(CODE_SUFFIXES):
        return False
    return "/" in token or token.endswith(".py")


def path_exists(token: str) -> bool:
    """``token`` names an existing file or folder: from a base folder, or as the end of a path.
    Capitalised words (NAME, FILE) and ``*`` match any name."""
    pattern = PLACEHOLDER.sub("*", token.removeprefix("./"))
    is_dir = pattern.endswith("/")
    files = all_files()
    for base in PATH_BASES:
        prefix = base.relative_to(ROOT).as_posix()
        full = pattern if prefix == "." else f"{prefix}/{pattern}"
        if any(fnmatch.fnmatchcase(f, full) for f in files):
            return True
    # the end of some path: "mavlink/attitude.py", "sample_clock/", or a bare "writer.py"
    tail = "*/" + pattern
    return any(fnmatch.fnmatchcase(f, tail) for f in files if f.endswith("/") == is_dir)


# --------------------------------------------------------------------------- modules
def module_problem(dotted: str) -> str | None:
    """None when ``dotted`` is an importable module or an attribute of one, else why not."""
    from ahrs_service import _moved

    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        name = ".".join(parts[:i])
        moved = _moved.new_path(name)
        if moved is not None:
            return f"{dotted}: {name} moved to {moved}"
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                found = importlib.util.find_spec(name) is not None
        except ModuleNotFoundError:
            found = False
        except ImportError as exc:  # an optional dependency missing: cannot tell
            pytest.skip(f"{name}: {exc}")
        if not found:
            continue
        try:
            obj = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and not exc.name.startswith("ahrs_service"):
                return None  # needs an extra that is not installed: not the docs' fault
            raise
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return f"{dotted}: {type(obj).__name__} {name} has no {attr!r}"
            obj = getattr(obj, attr)
            name = f"{name}.{attr}"
        return None
    return f"{dotted}: no such module"


# --------------------------------------------------------------------------- commands
@lru_cache(maxsize=None)
def cli_parser() -> argparse.ArgumentParser:
    from ahrs_service.cli import build_parser

    return build_parser()


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The subcommands argparse knows under ``parser`` (empty when it has none)."""
    for action in parser._actions:  # argparse keeps them only here
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def options(parser: argparse.ArgumentParser) -> set[str]:
    return set(parser._option_string_actions)


def command_problems(words: list[str]) -> list[str]:
    """Problems of one ``ahrs-service …`` invocation, ``words`` being what follows the name.

    Brackets, ellipses and ``a|b`` alternatives are read as the usage notation they are."""
    words = [w.strip("[](){},") for w in words]
    cut = next((i for i, w in enumerate(words) if w in SHELL_STOPS or w.startswith("#")), len(words))
    words = [w for w in words[:cut] if w and w not in {"…", "...", "|"}]
    if not words or words[0].startswith("-"):
        return []  # ``ahrs-service --help`` or the bare name
    shown = "ahrs-service " + " ".join(words)
    parser = cli_parser()
    commands = subcommands(parser)
    if PLACEHOLDER.fullmatch(words[0]):
        return []
    if words[0] not in commands:
        return [f"{shown}: no command {words[0]!r} (have {', '.join(sorted(commands))})"]
    parser = commands[words[0]]
    problems = []
    rest = words[1:]
    subs = subcommands(parser)
    if subs and rest and not rest[0].startswith("-") and not PLACEHOLDER.fullmatch(rest[0]):
        chosen = rest[0].split("|")
        missing = [c for c in chosen if c not in subs]
        if missing:
            return [f"{shown}: {words[0]} has no subcommand {', '.join(missing)} "
                    f"(have {', '.join(sorted(subs))})"]
        parser = subs[chosen[0]]
        rest = rest[1:]
    known = options(parser)
    for word in rest:
        for alternative in word.split("|"):
            if alternative.startswith("--"):
                flag = alternative.split("=", 1)[0]
                if flag not in known:
                    problems.append(f"{shown}: no option {flag}")
    return problems


def invocations(text: str) -> list[list[str]]:
    """The words after every ``ahrs-service`` in code spans and in fenced shell blocks."""
    found = []
    pieces = list(code_spans(text))
    for lang, body in fenced_blocks(text):
        if lang in ("", "sh", "bash", "shell", "console"):
            pieces.extend(body.splitlines())
    for piece in pieces:
        words = piece.split()
        for i, word in enumerate(words):
            if word == "ahrs-service" or word.endswith("/bin/ahrs-service"):
                found.append(words[i + 1:])
    return found


# --------------------------------------------------------------------------- one page
def problems_in(text: str, where: Path) -> list[str]:
    """Every reference of ``text`` (a page in folder ``where``) to code that does not exist."""
    problems = []
    spans = code_spans(text)
    shell_words = [w for lang, body in fenced_blocks(text) if lang in ("", "sh", "bash", "shell")
                   for w in body.split() if "/" in w]  # bare names there are the user's files
    for token in [*spans, *shell_words]:
        if looks_like_our_path(token) and not path_exists(token):
            problems.append(f"path {token}: not in the checkout")
    code_text = "\n".join([*spans, *(body for _, body in fenced_blocks(text))])
    for dotted in sorted(set(MODULE_PATH.findall(code_text))):
        problem = module_problem(dotted)
        if problem:
            problems.append(f"module {problem}")
    for words in invocations(text):
        problems.extend(f"command {p}" for p in command_problems(words))
    for target in links(text):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue  # a web address or an anchor on the same page
        path = target.split("#", 1)[0]
        if not (where / path).exists():
            problems.append(f"link {target}: no {path} beside {where.relative_to(ROOT).as_posix() or '.'}/")
    return sorted(set(problems))


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_doc_names_only_existing_code(doc: Path) -> None:
    problems = problems_in(doc.read_text(encoding="utf-8"), doc.parent)
    assert not problems, f"{doc.relative_to(ROOT)} names code that does not exist:\n  " + "\n  ".join(problems)


def test_checker_finds_made_up_references() -> None:
    made_up = """
A page that names `drivers/no_such_part.py`, the module `ahrs_service.no_such_module`, an
attribute `ahrs_service.estimators.no_such_function()`, an old path `ahrs_service.quaternion`,
the command `ahrs-service no-such-command`, `ahrs-service log no-such-sub`,
`ahrs-service run --no-such-option` and a link to [nowhere](no-such-page.md).

```sh
python benchmarks/no_such_benchmark.py
```
"""
    problems = "\n".join(problems_in(made_up, ROOT / "docs"))
    for expected in ("drivers/no_such_part.py", "ahrs_service.no_such_module",
                     "no_such_function", "moved to ahrs_service.core.quaternion",
                     "no-such-command", "no-such-sub", "--no-such-option", "no-such-page.md",
                     "benchmarks/no_such_benchmark.py"):
        assert expected in problems, f"the checker missed {expected}:\n{problems}"


def test_checker_accepts_real_references() -> None:
    real = """
`drivers/fifo.py`, `ahrs_service/estimators/tuned/NAME.json`, `estimators/tuned/`,
`mavlink/attitude.py`, `ahrs_service.estimators.run`, `ahrs_service.core.quaternion`,
`ahrs-service log plot flight.mcap --out flight.png`, `ahrs-service calibrate mag|accel|gyro`,
`ahrs-service compile [NAME … | --all]`, `../shared/data/broad/`, `/dev/i2c-1`,
`EKF2_EV_CTRL = 8`, [design](design.md), [vqf](https://github.com/dlaidig/vqf).
"""
    assert problems_in(real, ROOT / "docs") == []


def test_the_docs_name_every_board_of_the_registry_and_no_other() -> None:
    """The configuration reference lists the board registry's names with their buses, and each
    board has its row in the drivers' pages (``ahrs_service.drivers.boards.BOARDS``)."""
    from ahrs_service.drivers.boards import BOARDS

    reference = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    listed = re.search(r'^board = "\w+"\s+#\s*(.+)$', reference, re.M)
    assert listed, "docs/configuration.md: no board = … line"
    named = re.findall(r"[a-z0-9]+", re.sub(r"\([^)]*\)", "", listed.group(1)))
    assert named == list(BOARDS)
    for group in re.findall(r"((?:[a-z0-9]+ \| )*[a-z0-9]+) \(([^)]*)\)", listed.group(1)):
        boards, buses = group[0].split(" | "), {b.strip().lower() for b in group[1].split(" or ")}
        assert all(set(BOARDS[b].buses) == buses for b in boards), (boards, buses)
    pages = (ROOT / "docs" / "drivers.md").read_text(encoding="utf-8") + (ROOT / "docs" / "drivers-spi.md").read_text(encoding="utf-8")
    assert [b for b in BOARDS if not re.search(rf"^\| `{b}` \|", pages, re.M)] == []
