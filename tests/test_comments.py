"""Comments and docstrings state rules and reasons, not measurement history.

Scanned: every comment (``#``, found with :mod:`tokenize`) and docstring
(module, class and function, found with :mod:`ast`) in ``lodserver/**/*.py``,
and every ``//`` and ``/* */`` comment of ``static/*.js`` (``static/vendor/``
is three.js's, not ours).

The rule: a comment says what the code does and why. How fast it ran, on which
machine, on which day, and what it was before belongs in the commit message or
``bench/README.md``, where the figure sits beside the commit it measured. So a
comment fails, named ``file:line``, when it holds

- a **timing figure**: a number followed by a time unit (ns, us, µs, ms, s,
  sec, seconds, min, minutes, h, hours, cycles): "0.11 s", "151 -> 108 ns",
  "2-6 s", "~15 ms", "16k cycles". A bare ``s`` counts only after a space or a decimal
  ("0.5 s", "0.5s"), so shapes like ``(r, 4s)`` and plurals like "304s" pass;
- a **date**: ``2026-12-02``, or a month and year ("Nov 2026", "December 2, 2026");
- a **speed-up or before/after figure**: "20x faster", "1.75 times as long",
  "15% less time", "30% of this step's time", "a 2x speed-up", or an arrow
  from one figure to another with a unit ("151 -> 108 ns", "370 -> 55 MB").
  An arrow between bare numbers ("-1 -> 0", a mapping) passes.

A timing figure that is a *setting* passes: what the code does, not how fast it
ran. It is a setting when a word naming one stands within a few words of it
(timeout, wait, lease, interval, delay, retry, Retry-After, backoff, idle, poll,
default, deadline, expiry, max-age, clamp, throttle) and its sentence says
nothing of a measurement (took, takes, measured, spent, ran, faster, slower,
CPU); or when the comment
sits on (or right above) a constant whose name says it is a time (``*_SECONDS``,
``*_MS``, ``*_TIMEOUT``, ...) and the figure is that constant's own value. So "wait : float, seconds (default 30 s)" and
``RETRY_MS = 500  // 500 ms before the first retry`` pass; "took 0.5 s" does not.
Years alone (paper citations: "Hoppe 1996"), lengths and sizes ("64 KiB",
"(n, 3) float64", "3 x 3", "O(n log n)") are not figures of this kind.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_NUMBER = r"(?<![\w.])~?\d+(?:[.,]\d+)*"
_RANGE = _NUMBER + r"(?:\s*(?:-|–|to)\s*\d+(?:[.,]\d+)*)?"
TIMING = re.compile(
    _RANGE + r"(?:"
    r"k?\s*(?:ns|us|µs|μs|ms|sec|secs|[Ss]econds?|[Mm]inutes?|[Hh]ours?|cycles)\b"  # any spacing
    r"|\s+(?:s|min|mins|h)\b(?!\()"                                 # bare units after a space
    r"|(?<=\.\d)s\b|(?<=\.\d\d)s\b"                                 # "0.5s", "0.25s"
    r")")
DATE = re.compile(
    r"\b(?:19|20)\d\d-\d\d-\d\d\b"
    r"|\b(?:Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Sept|Oct|Nov|Dec)[a-z]*\.?\s+(?:\d{1,2},?\s+)?(?:19|20)\d\d\b")
_FIGURE = r"\d+(?:[.,]\d+)*"
_UNIT = r"(?:ns|us|µs|μs|ms|s|sec|seconds|min|minutes|h|hours|[KMGT]i?B|bytes|%|x|cycles)"
SPEEDUP = re.compile("|".join([
    _FIGURE + r"\s*(?:x|×|times)\s+(?:faster|slower|quicker|as fast|as slow|as long|the time"
              r"|less time|more time)\b",
    _FIGURE + r"\s*(?:x|×)\s+speed-?up",
    r"speed-?up\s+of\s+" + _FIGURE,
    _FIGURE + r"\s*%\s+(?:faster|slower|quicker|less\s+(?:time|CPU|memory)|more\s+(?:time|CPU))",
    _FIGURE + r"\s*%\s+of\s+(?:the|its|this|a|each)\s+(?:[\w'-]+\s+){0,2}"
              r"(?:time|step|CPU|encode|decode|build|ranking|run|kernel)\b",
    # an arrow from one figure to another with a unit: "151 -> 108 ns", not "-1 -> 0"
    _FIGURE + r"\s*" + _UNIT + r"?\s*(?:->|→|=>)\s*~?" + _FIGURE + r"\s*" + _UNIT + r"(?![\w-])",
]), re.IGNORECASE)

SETTING_WORDS = re.compile(
    r"timeouts?|time-out|\bwaits?\b|\bwaited\b|\bwaiting\b|\blease|\binterval|\bdelay|\bretr(?:y|ies)"
    r"|retry-after|backoff|\bidle\b|\bpoll|\bdefault|\bdeadline|\bexpir|max-age|\bclamp|throttl",
    re.IGNORECASE)
MEASURED_WORDS = re.compile(
    r"\btook\b|\btakes?\b|\btaking\b|\bmeasured\b|\bspent\b|\bspends?\b|\bran\b|\bfaster\b|\bslower\b|\bCPU\b",
    re.IGNORECASE)
# A constant or setting whose name says it is a time, and the value given to it.
TIME_CONSTANT = re.compile(
    r"^\s*(?:(?:export\s+)?(?:const|let|var)\s+)?"
    r"\w*(?:seconds|_ms|_s|timeout|_wait|interval|delay|_ttl|max_age)\s*(?::[^=]*)?=(?!=)(?P<value>.*)",
    re.IGNORECASE)
# How near a timing figure (characters either side) the word naming its setting must be.
SETTING_REACH = 40
_SENTENCE_END = re.compile(r"[.;!?](?=\s|$)|\n\s*\n")


# ---------------------------------------------------------------------------
# Where the comments are: (path, first line, text, code line it describes)
# ---------------------------------------------------------------------------

def _blocks(found, lines):
    """Comment lines ``(line, text, trailing)`` joined into blocks (consecutive
    whole-line comments; a trailing comment alone): (first line, text, the code
    line the block sits on, or the first one below it)."""
    blocks = []         # [first line, [texts], last line, trailing]
    for row, text, trailing in found:
        if blocks and not trailing and not blocks[-1][3] and blocks[-1][2] == row - 1:
            blocks[-1][1].append(text)
            blocks[-1][2] = row
        else:
            blocks.append([row, [text], row, trailing])
    for first, texts, last, trailing in blocks:
        if trailing:
            code = lines[first - 1]
        else:
            code = next((line for line in lines[last:] if line.strip()), "")
        yield first, "\n".join(texts), code


def python_comments(path: Path):
    """Comment blocks (consecutive ``#`` lines, or one trailing comment) and
    docstrings of one module: (first line, text, the code line they sit on or above)."""
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    found = []          # (line, text, trailing)
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            row, col = token.start
            found.append((row, token.string.lstrip("#").strip(),
                          bool(lines[row - 1][:col].strip())))
    yield from _blocks(found, lines)
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = node.body[0] if node.body else None
            if (isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant)
                    and isinstance(doc.value.value, str)):
                yield doc.lineno, doc.value.value, ""


def js_comments(path: Path):
    """``//`` blocks and ``/* */`` comments of one script, skipping strings,
    template literals and regular expression literals: (first line, text, code line)."""
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    found = []          # (line, text, trailing)
    i, n, line = 0, len(source), 1
    last_significant = ""       # the last non-space character of code, for regex literals
    templates = []              # brace depths of the template literals we are inside
    depth = 0
    while i < n:
        c = source[i]
        if c == "\n":
            line += 1
            i += 1
            continue
        if source.startswith("//", i):
            end = source.find("\n", i)
            end = n if end < 0 else end
            trailing = bool(lines[line - 1][:i - source.rfind("\n", 0, i) - 1].strip())
            found.append((line, source[i + 2:end].strip(), trailing))
            i = end
            continue
        if source.startswith("/*", i):
            end = source.find("*/", i + 2)
            end = n if end < 0 else end
            text = source[i + 2:end]
            for k, part in enumerate(text.split("\n")):
                found.append((line + k, part.strip(" *"), k == 0 and False))
            line += text.count("\n")
            i = end + 2
            continue
        if c in "'\"":
            i += 1
            while i < n and source[i] != c and source[i] != "\n":
                i += 2 if source[i] == "\\" else 1
            i += 1
            last_significant = c
            continue
        if c == "`" or (c == "}" and templates and templates[-1] == depth):
            if c == "}":
                templates.pop()
            i += 1
            while i < n and source[i] != "`" and not source.startswith("${", i):
                if source[i] == "\n":
                    line += 1
                i += 2 if source[i] == "\\" else 1
            if source.startswith("${", i):
                templates.append(depth)
                i += 2
            else:
                i += 1
            last_significant = "`"
            continue
        if c == "/" and (last_significant in "" "(,=:[!&|?{};+-*%<>~^" or
                         re.search(r"\b(?:return|typeof|case|in|of|yield|await)\s*$",
                                   source[max(0, i - 12):i])):
            i += 1
            in_class = False
            while i < n and source[i] != "\n" and (source[i] != "/" or in_class):
                if source[i] == "\\":
                    i += 1
                elif source[i] == "[":
                    in_class = True
                elif source[i] == "]":
                    in_class = False
                i += 1
            i += 1
            last_significant = "/"
            continue
        if c == "{":
            depth += 1
        elif c == "}":
            depth -= 1
        if not c.isspace():
            last_significant = c
        i += 1
    yield from _blocks(found, lines)


def all_comments():
    for path in sorted((ROOT / "lodserver").rglob("*.py")):
        for first, text, code in python_comments(path):
            yield path.relative_to(ROOT), first, text, code
    for path in sorted((ROOT / "static").glob("*.js")):
        for first, text, code in js_comments(path):
            yield path.relative_to(ROOT), first, text, code


# ---------------------------------------------------------------------------
# The rule
# ---------------------------------------------------------------------------

def sentence_around(text: str, start: int, end: int) -> str:
    """The sentence of ``text`` that holds ``text[start:end]``."""
    begin = 0
    for m in _SENTENCE_END.finditer(text, 0, start):
        begin = m.end()
    m = _SENTENCE_END.search(text, end)
    return text[begin:m.start() if m else len(text)]


def is_setting(text: str, start: int, end: int, code: str) -> bool:
    """Whether the timing figure ``text[start:end]`` is a setting, not a measurement."""
    constant = TIME_CONSTANT.match(code)
    if constant:
        value = {float(x) for x in re.findall(r"\d+(?:\.\d+)?",
                                              constant.group("value").replace("_", ""))}
        numbers = [float(x) for x in re.findall(r"\d+(?:\.\d+)?", text[start:end])]
        if numbers and all(x in value for x in numbers):
            return True     # the figure is the constant's own value
    sentence = sentence_around(text, start, end)
    near = text[max(0, start - SETTING_REACH):end + SETTING_REACH]
    return bool(SETTING_WORDS.search(near)) and not MEASURED_WORDS.search(sentence)


def problems(text: str, code: str = ""):
    """(offset in ``text``, what, the words) for every figure the rule refuses."""
    for m in TIMING.finditer(text):
        if not is_setting(text, m.start(), m.end(), code):
            yield m.start(), "a timing figure", m.group()
    for m in DATE.finditer(text):
        yield m.start(), "a date", m.group()
    for m in SPEEDUP.finditer(text):
        yield m.start(), "a speed-up or before/after figure", m.group()


def violations():
    found = []
    for path, first, text, code in all_comments():
        for at, what, words in problems(text, code):
            line = first + text.count("\n", 0, at)
            found.append(f"{path}:{line}: {what} ({words!r}): say why, and put the figure "
                         f"in the commit message or bench/README.md")
    return found


# ---------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------

def test_no_comment_or_docstring_holds_a_timing_a_date_or_a_speed_up():
    found = violations()
    assert not found, "\n".join(found)


def test_the_scan_reaches_every_file_and_kind_of_comment():
    python = list((ROOT / "lodserver").rglob("*.py"))
    scripts = list((ROOT / "static").glob("*.js"))
    seen = {path for path, *_ in all_comments()}
    assert {p.relative_to(ROOT) for p in python + scripts if p.stat().st_size} <= seen
    assert not any(p.parts[:2] == ("static", "vendor") for p in seen)
    docstrings = sum(1 for p in python for _, _, code in python_comments(p) if code == "")
    blocks = sum(1 for p in scripts for _ in js_comments(p))
    assert docstrings > 500 and blocks > 300, (docstrings, blocks)


@pytest.mark.parametrize("text", [
    "ranking a part of the 1.1M bunny: 0.53 s against 0.19 s of CPU",
    "(a part of the 1.1M bunny: 151 -> 108 ns an edge)",
    "decimates at about 4.7 us a collapse",
    "a json level of 65k faces is about 2 MB, encoded in ~15 ms.",
    "numpy's repeat-and-index took 0.1 s at 1M faces",
    "took 0.5s of a run",
    "costs 2-6 s of GPU time",
    "a frame blocks the main thread for 100-500 ms",
    "135 parts take 0.1-0.3 s on 2 loaded cores",
    "the speed run of 2026-12-02 afternoon",
    "measured in Nov 2026",
    "with repeated rows summed (np.add.at, 20x faster)",
    "in 1.75 times as long",
    "(1.1M bunny: about 15% less CPU time)",
    "their load and store took about 30% of this step",
    "a 1.8x speed-up",
    "a cached level's p99 from 80 -> 55 ms",
    "the default is 30 s, which took 2 s to reach",     # a measurement beside a setting
    "a frame blocks the main thread for 100-500 ms (the canvas is read back)",
    "a collapse took about 16k cycles against about 11k",
    "(measured 15% of the forward encode on a million faces)",
])
def test_the_rule_refuses_history(text):
    assert list(problems(text)), text


@pytest.mark.parametrize("text, code", [
    # a time constant's comment, but the figure is a measurement, not its value
    ("its GPU work (0.4-1 s under software GL) then overlaps", "const ENVIRONMENT_AHEAD_MS = 1500;"),
    ("reading every vertex at random took 0.5 s", "_SIDE_SAMPLE = 65_536"),
    ("a build took 45 s on 2 cores", "LEASE_SECONDS = 60.0"),
    ("its GPU work (0.4-1 s under software GL) then overlaps the download rather than delaying", ""),
])
def test_a_time_constant_excuses_only_its_own_value(text, code):
    assert list(problems(text, code)), text


@pytest.mark.parametrize("text, code", [
    ("Hoppe 1996, Garland & Heckbert 1997; Lindstrom 2000", ""),
    ("positions (n, 3) float64, faces (m, 3) int64; a 3 x 3 solve", ""),
    ("O(n log n) in the number of faces; 3 x 21 = 63 bits", ""),
    ("Joints (r, 4s) and weights (r, 4s) of s influence sets", ""),
    ("Security headers on every response, errors, redirects and 304s included.", ""),
    ("Signed -> unsigned: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ...; +1 -> 1, -1 -> 0", ""),
    ("read from its last 64 KiB; a 256 MB zip; 2^21 * 96 bytes = 201 MB", ""),
    ("growing at most 4x a packet", ""),
    ("wait : float\n    Seconds a request may wait (default 30 s).", ""),
    ("The server closes a connection after a 30 s idle timeout.", ""),
    ("without the >= 4 ms clamp of nested setTimeout.", ""),
    ("a client is told to retry after 5 s", ""),
    ("the first retry waits 500 ms, doubling", ""),
    ("seconds a client waits", "RETRY_AFTER = 5"),
    ("500 ms before the first retry", "const RETRY_BASE_MS = 500;"),
    ("5 s between progress writes", "PROGRESS_SECONDS = 5.0"),
])
def test_the_rule_lets_rules_and_settings_pass(text, code):
    assert not list(problems(text, code)), list(problems(text, code))


def test_js_strings_and_regular_expressions_are_not_comments(tmp_path):
    script = tmp_path / "a.js"
    script.write_text(
        "const url = 'http://example.com/a'; // a comment\n"
        "const re = /^\\/+/; const t = `${a} // not a comment ${`inner // no`}`;\n"
        "/* block\n   two */ const x = 1 / 2; // after\n")
    texts = [(line, text) for line, text, _ in js_comments(script)]
    assert texts == [(1, "a comment"), (3, "block\ntwo"), (4, "after")], texts
