"""The documentation says what the code does: README.md and docs/*.md.

* README.md stays short (at most 250 lines; everything else lives in docs/).
* Every ```python block that is marked safe to run runs without error, in a subprocess with the
  repository as working directory.  The marker: the fence line is exactly ```python and the
  block is not preceded by ``<!-- not run -->`` (among the HTML comment lines right above the
  fence).  Mark a block ``<!-- not run -->`` when it needs hardware, ROS, a long run or files the
  repository does not hold.
* No page holds a ``<!-- CHECK-... -->`` marker (text left to be checked against the code).
* Every relative link (and its ``#anchor``) points to a file (and heading) that exists, and so
  does every repository path named in inline code (``fitting/engine.py``, ``calibration/bayes/``);
  the table of subpackages in docs/architecture.md names only modules its subpackage holds.
* Every ``imu-array`` command named in README's CLI table exists, and so does every ``--option``
  in its row; every ``imu-array ...`` command line in the docs uses existing commands and options;
  docs/cli.md documents exactly the options each command has.
* The parameter tables of docs/nodes.md match ``imu_array_ros/nodes/parameters.py`` (names,
  defaults, ranges, choices), every ``-p name:=`` given to a node exists, and the launch-argument
  table matches the launch file.

The CLI is run as ``sys.executable -m imu_array_ros <command> --help`` (in parallel, cached).
"""

from __future__ import annotations

import ast
import functools
import os
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = REPO / "docs"
PAGES = [README, *sorted(DOCS.glob("*.md"))]
MAX_README_LINES = 250
NOT_RUN = "<!-- not run -->"
BLOCK_TIMEOUT_S = 300


def _rel(path: Path) -> str:
    return str(path.relative_to(REPO))


# --------------------------------------------------------------------------- markdown parsing


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # 1-based line of the opening fence
    lang: str  # the fence's info string, e.g. "python", "bash", ""
    code: str
    markers: tuple[str, ...]  # HTML comment lines right above the fence

    @property
    def runs(self) -> bool:
        return self.lang == "python" and NOT_RUN not in self.markers

    @property
    def id(self) -> str:
        return f"{_rel(self.path)}:{self.line}"


def code_blocks(path: Path) -> list[Block]:
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = re.match(r"^```(.*)$", lines[i])
        if not m:
            i += 1
            continue
        start, lang = i, m.group(1).strip()
        markers, j = [], start - 1
        while j >= 0 and lines[j].strip().startswith("<!--") and lines[j].strip().endswith("-->"):
            markers.append(lines[j].strip())
            j -= 1
        i += 1
        body = []
        while i < len(lines) and lines[i].strip() != "```":
            body.append(lines[i])
            i += 1
        assert i < len(lines), f"{_rel(path)}:{start + 1}: code block never closed"
        blocks.append(Block(path, start + 1, lang, "\n".join(body) + "\n", tuple(markers)))
        i += 1
    return blocks


def prose(path: Path) -> str:
    """The page without its fenced code blocks (lines kept, so positions stay meaningful)."""
    out, inside = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            inside = not inside
            out.append("")
            continue
        out.append("" if inside else line)
    return "\n".join(out)


def inline_code(text: str) -> list[str]:
    return re.findall(r"`([^`\n]+)`", text)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading: its text
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@functools.lru_cache(maxsize=None)
def anchors(path: Path) -> frozenset[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in prose(path).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        s = slug(m.group(1))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return frozenset(out)


def section(path: Path, title: str, level: int = 2) -> str:
    """The text between the heading ``title`` and the next heading of the same or a higher level."""
    text = path.read_text(encoding="utf-8")
    hashes = "#" * level
    m = re.search(rf"^{hashes} {re.escape(title)}\n(.*?)(?=^#{{1,{level}}} |\Z)", text, flags=re.S | re.M)
    assert m, f"{_rel(path)}: no section {hashes} {title}"
    return m.group(1)


# --------------------------------------------------------------------------- the command line


COMMAND_WORD = re.compile(r"^[a-z][a-z-]*$")
LONG_OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _help(path: tuple[str, ...]) -> str:
    proc = subprocess.run([sys.executable, "-m", "imu_array_ros", *path, "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=60,
                          env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 0, f"imu-array {' '.join(path)} --help: {proc.stderr.strip()}"
    return proc.stdout


def _subcommands(help_text: str) -> set[str]:
    """The sub-commands argparse lists under a COMMAND / METHOD argument (indented by exactly 4)."""
    return set(re.findall(r"^ {4}([a-z][a-z-]*)(?:\s|$)", help_text, flags=re.M))


@functools.lru_cache(maxsize=None)
def cli_help() -> dict[tuple[str, ...], str]:
    """``--help`` of the program, of every command and of every ``calibrate`` method."""
    top = _help(())
    paths = [(c,) for c in sorted(_subcommands(top))]
    assert paths, top
    with ThreadPoolExecutor(max_workers=4) as pool:
        texts = dict(zip(paths, pool.map(_help, paths)))
    nested = [p + (s,) for p, text in texts.items() for s in sorted(_subcommands(text))]
    with ThreadPoolExecutor(max_workers=4) as pool:
        texts.update(zip(nested, pool.map(_help, nested)))
    texts[()] = top
    return texts


def command_path(words: list[str]) -> tuple[str, ...]:
    """The command words at the start of ``words`` (after ``imu-array``): as deep as the program nests."""
    helps = cli_help()
    path: tuple[str, ...] = ()
    for w in words:
        if not COMMAND_WORD.match(w) or path + (w,) not in helps:
            break
        path += (w,)
    return path


def options_of(path: tuple[str, ...]) -> set[str]:
    return set(LONG_OPTION.findall(cli_help()[path]))


def command_lines(path: Path) -> list[tuple[int, str]]:
    """(line, text after ``imu-array``) of every command line in the page's code: blocks and spans."""
    found = []
    text = path.read_text(encoding="utf-8").splitlines()
    in_block = False
    for n, line in enumerate(text, 1):
        if line.startswith("```"):
            in_block = not in_block
            continue
        pieces = [line] if in_block else inline_code(line)
        for piece in pieces:
            for m in re.finditer(r"(?:^|\s)(?:\S*bin/)?imu-array\s+(.*)", piece):
                rest = re.split(r"\s(?:&&|\|\||\||;|&|#)(?:\s|$)|\s&$", m.group(1))[0]
                found.append((n, rest))
    return found


# --------------------------------------------------------------------------- (a) README length


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines; at most {MAX_README_LINES} (move the rest to docs/)"


def test_docs_exist_and_are_linked_from_the_readme():
    assert len(PAGES) > 1, "docs/ holds no page"
    linked = set(re.findall(r"\]\((docs/[^)#\s]+)", README.read_text(encoding="utf-8")))
    missing = [_rel(p) for p in PAGES[1:] if _rel(p) not in linked]
    assert not missing, f"docs pages the README does not link: {missing}"


#: abbreviations a newcomer meets in the README -> words of their expansion, given where they first appear
README_TERMS = {"CRB": "Cramér–Rao bound", "NIS": "normalised innovation squared"}


@pytest.mark.parametrize("term", sorted(README_TERMS))
def test_readme_spells_out_a_term_where_it_first_appears(term):
    """The first README line (with the line after it) that uses CRB or NIS says what it stands for."""
    lines = README.read_text(encoding="utf-8").splitlines()
    first = next(n for n, line in enumerate(lines) if re.search(rf"\b{term}\b", line))
    near = " ".join(lines[max(first - 1, 0):first + 2])
    assert README_TERMS[term] in near, f"README.md:{first + 1}: {term} used before it is spelled out: {lines[first]}"


# --------------------------------------------------------------------------- (b) python blocks


PYTHON_BLOCKS = [b for p in PAGES for b in code_blocks(p) if b.runs]


@pytest.mark.parametrize("block", PYTHON_BLOCKS, ids=[b.id for b in PYTHON_BLOCKS])
def test_python_block_runs(block):
    env = {**os.environ, "MPLBACKEND": "Agg", "PYTHONDONTWRITEBYTECODE": "1"}
    proc = subprocess.run([sys.executable, "-c", block.code], cwd=REPO, capture_output=True, text=True,
                          timeout=BLOCK_TIMEOUT_S, env=env)
    assert proc.returncode == 0, (f"{block.id}: the block failed\n--- stderr (tail) ---\n"
                                  + "\n".join(proc.stderr.strip().splitlines()[-15:]))


def test_every_python_fence_is_exact_or_marked():
    """A python-looking fence that is not exactly ```python would silently never run: refuse it."""
    odd = [b.id for p in PAGES for b in code_blocks(p)
           if b.lang.lower().startswith("py") and b.lang != "python"]
    assert not odd, f"python blocks with another fence (use ```python, and {NOT_RUN} if it must not run): {odd}"


# --------------------------------------------------------------------------- (c) links


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _links(path: Path) -> list[tuple[int, str]]:
    out = []
    for n, line in enumerate(prose(path).splitlines(), 1):
        line = re.sub(r"`[^`\n]*`", "code", line)
        out += [(n, m.group(1)) for m in LINK.finditer(line)]
    return out


@pytest.mark.parametrize("page", PAGES, ids=[_rel(p) for p in PAGES])
def test_relative_links_resolve(page):
    bad = []
    for n, target in _links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.exists():
            bad.append(f"{_rel(page)}:{n}: {target}: no such file")
            continue
        if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{_rel(page)}:{n}: {target}: no heading #{anchor} in {dest.name}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("page", PAGES, ids=[_rel(p) for p in PAGES])
def test_no_check_markers_are_left(page):
    left = [f"{_rel(page)}:{n}: {line.strip()}" for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
            if re.search(r"<!--\s*CHECK-", line)]
    assert not left, "text marked to be checked against the code (check it, then remove the marker):\n" + "\n".join(left)


# --------------------------------------------------------------------------- (c') paths named in the text


#: a repository path in inline code: a module, a directory, or a file under a directory
PATH_LIKE = re.compile(r"^[\w.-]+(?:/[\w.-]+)*(?:\.py|/)$|^[\w.-]+(?:/[\w.-]+)+\.(?:md|yaml|sh|json|png)$")
SKIP_DIRS = {".git", ".venv", "__pycache__", "build", "install", "log"}


@functools.lru_cache(maxsize=None)
def repo_paths() -> tuple[str, ...]:
    """Every file (``a/b.py``) and directory (``a/``) of the working tree, relative to the repository."""
    out = []
    for root, dirs, files in os.walk(REPO):
        dirs[:] = [d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info")]
        rel = Path(root).relative_to(REPO)
        out += [(rel / f).as_posix() for f in files] + [(rel / d).as_posix() + "/" for d in dirs]
    return tuple(out)


def _named_path_exists(token: str, within: str = "") -> bool:
    """``token`` is a path of the repository (or of ``within``), or the end of one (``engine.py``,
    ``fitting/engine.py``, ``bayes/``)."""
    return any(p.startswith(within) and (p in (within + token, token) or p.endswith("/" + token))
               for p in repo_paths())


@pytest.mark.parametrize("page", PAGES, ids=[_rel(p) for p in PAGES])
def test_paths_named_in_the_text_exist(page):
    bad = []
    for n, line in enumerate(prose(page).splitlines(), 1):
        for token in inline_code(line):
            if (not PATH_LIKE.match(token) or token.startswith(("lib/", "../"))
                    or token.split("/")[0].isupper()):
                continue  # the install tree of colcon; outside the repository; placeholders (DIR/report.md)
            if not _named_path_exists(token):
                bad.append(f"{_rel(page)}:{n}: {token}: no such file or directory in the repository")
    assert not bad, "\n".join(bad)


def test_architecture_table_names_only_modules_of_each_subpackage():
    text = section(DOCS / "architecture.md", "What each subpackage holds")
    table = text[text.index("| path |"):].split("\n\n")[0]  # the first table: the package's subpackages
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    assert rows
    bad = []
    for row in rows:
        cells = [c.strip() for c in row.strip().strip("|").split(" | ")]
        first = inline_code(cells[0])
        within = f"imu_array_ros/{first[0]}" if len(first) == 1 and first[0].endswith("/") else "imu_array_ros/"
        for token in inline_code(cells[1]):
            if (token.endswith(".py") or token.endswith("/")) and not _named_path_exists(token, within):
                bad.append(f"{cells[0]}: {token}: not in {within}")
    assert not bad, "\n".join(bad)


# --------------------------------------------------------------------------- (d) the CLI


def _readme_cli_rows() -> list[str]:
    rows = [line for line in section(README, "The command line").splitlines() if line.startswith("| `imu-array")]
    assert rows, "README: no CLI table rows in '## The command line'"
    return rows


def test_readme_cli_table_commands_and_options_exist():
    helps = cli_help()
    bad, named = [], set()
    for row in _readme_cli_rows():
        first = inline_code(row)[0]
        words = first.split()[1:]
        path = command_path(words)
        if not path or (words[len(path):] and COMMAND_WORD.match(words[len(path)])):
            bad.append(f"{first}: not a command of imu-array")
            continue
        named.add(path)
        if len(path) == 1:
            assert path[0] in _subcommands(helps[()])  # listed in imu-array --help
        missing = sorted(set(LONG_OPTION.findall(row)) - options_of(path))
        if missing:
            bad.append(f"imu-array {' '.join(path)}: no option {', '.join(missing)}")
    assert not bad, "\n".join(bad)
    leaves = {p for p in helps if p and not any(q[:len(p)] == p and len(q) > len(p) for q in helps)}
    assert leaves <= named, f"commands missing from README's CLI table: {sorted(leaves - named)}"


@pytest.mark.parametrize("page", PAGES, ids=[_rel(p) for p in PAGES])
def test_documented_command_lines_use_existing_commands_and_options(page):
    bad = []
    for n, rest in command_lines(page):
        words = rest.split()
        path = command_path(words)
        if words and not path and COMMAND_WORD.match(words[0]):
            bad.append(f"{_rel(page)}:{n}: imu-array {words[0]}: no such command")
            continue
        if path and words[len(path):] and COMMAND_WORD.match(words[len(path)]) and path[0] == "calibrate":
            bad.append(f"{_rel(page)}:{n}: imu-array {' '.join(words[:len(path) + 1])}: no such command")
            continue
        missing = sorted(set(LONG_OPTION.findall(rest)) - options_of(path))
        if missing:
            bad.append(f"{_rel(page)}:{n}: imu-array {' '.join(path)}: no option {', '.join(missing)}")
    assert not bad, "\n".join(bad)


def test_cli_page_documents_exactly_the_options_of_every_command():
    page = DOCS / "cli.md"
    helps = cli_help()
    bad = []
    leaves = [p for p in helps if p and not any(q[:len(p)] == p and len(q) > len(p) for q in helps)]
    for path in leaves:
        title = f"`imu-array {' '.join(path)}`"
        text = section(page, title)
        table = {o for line in text.splitlines() if line.startswith("| `-")
                 for o in LONG_OPTION.findall(line.split("|")[1])}
        have = options_of(path) - {"--help"}
        if have - set(LONG_OPTION.findall(text)):
            bad.append(f"{title}: options not documented: {sorted(have - set(LONG_OPTION.findall(text)))}")
        if table - have:
            bad.append(f"{title}: documented options the command does not have: {sorted(table - have)}")
    assert not bad, "\n".join(bad)


# --------------------------------------------------------------------------- nodes: parameters and launch file


def _param_table(text: str) -> list[list[str]]:
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    return [[c.strip() for c in row.strip().strip("|").split(" | ")] for row in rows]


@pytest.mark.parametrize("node", ["driver_node", "fusion_node", "calibration_node"])
def test_node_parameter_tables_match_the_declarations(node):
    from imu_array_ros.nodes.parameters import NODE_PARAMS

    rows = _param_table(section(DOCS / "nodes.md", node, level=3))
    params = NODE_PARAMS[node]
    assert [r[0].strip("`") for r in rows] == [p.name for p in params]
    for (name, default, rng, _meaning), p in zip(rows, params):
        value = yaml.safe_load(default.strip("`"))
        assert type(value) is type(p.default) and value == p.default, (name, default, p.default)
        if p.required:
            assert rng == "required", name
        elif p.choices:
            assert tuple(c.strip() for c in rng.split("\\|")) == tuple(p.choices), name
        elif p.low is not None:
            low, high = (float(x) for x in rng.strip("[]").split(","))
            assert (low, high) == (float(p.low), float(p.high)), name
        else:
            assert rng == "", name


@pytest.mark.parametrize("page", PAGES, ids=[_rel(p) for p in PAGES])
def test_node_parameters_given_in_the_docs_exist(page):
    from imu_array_ros.nodes.parameters import NODE_PARAMS

    bad = []
    for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
        for m in re.finditer(r"\b(driver_node|fusion_node|calibration_node)\s+--ros-args(.*?)(?:&|$)", line):
            known = {p.name for p in NODE_PARAMS[m.group(1)]}
            given = set(re.findall(r"-p\s+([A-Za-z_]\w*):=", m.group(2)))
            if given - known:
                bad.append(f"{_rel(page)}:{n}: {m.group(1)} has no parameter {sorted(given - known)}")
    assert not bad, "\n".join(bad)


def test_launch_argument_table_matches_the_launch_file():
    tree = ast.parse((REPO / "launch" / "imu_array.launch.py").read_text(encoding="utf-8"))
    declared = next([k.value for k in node.value.keys] for node in ast.walk(tree)
                    if isinstance(node, ast.Assign) and isinstance(node.value, ast.Dict)
                    and any(isinstance(t, ast.Name) and t.id == "args" for t in node.targets))
    rows = _param_table(section(DOCS / "nodes.md", "Launch file"))
    assert [r[0].strip("`") for r in rows] == declared
