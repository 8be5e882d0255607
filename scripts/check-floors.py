#!/usr/bin/env python3
"""Checks that the top-level modules of src/, and the files of each folder, import each other without a cycle.

Every `crate::X` path in the code (a `use crate::...` line, grouped as in
`use crate::{a::X, b::{Y, Z}}`, or a path written inline such as
`crate::x::f()`, or a path in an attribute's string, as serde's
`deserialize_with = "crate::x::f"`) is an arrow from the module of its file to X. The floors
(docs/architecture.md) want every arrow to point down; a cycle is a set of
modules that reach one another (a strongly connected component), and it
is printed with the file:line of each import between its members.

Inside the folders the files stand on floors too: each `crate::`,
`super::` and `self::` path (and a child module named by itself in its
parent) is an arrow from its file to the file that defines what it names,
followed through `pub use` re-exports (globs included); a `pub use` only
hands names on and is no arrow of its own, so a folder's `mod.rs` stands on
top of its files; `#[cfg(test)]` modules are left out. A circle of files is
a set of files that reach one another, printed with the lines that close it.

Known cycles may be listed in an allow-list file, one per line, by their
members separated by spaces (`#` starts a comment): top-level modules by
name, circles of files by their paths under src/. The check fails on a
cycle that is not listed exactly, and on a listed one that no longer
exists: the list can only shrink, each time to what the code is.

    scripts/check-floors.py [--src DIR] [--allow FILE] [--doc FILE]
    scripts/check-floors.py --picture [--write]

It also checks that docs/architecture.md holds the picture of the floors
that the code draws (`--picture` prints it, `--picture --write` redraws it
in the doc): each top-level module on the floor one above the highest it
imports.

Exit status: 0 without unlisted cycles, 1 otherwise, 2 on bad usage.
Python's standard library only.
"""

import argparse
import os
import re
import sys

# Files whose `crate::` is not a module of the library: the crate roots.
ROOTS = {"lib.rs", "main.rs"}

PATH_START = re.compile(r"\bcrate\s*::\s*")
IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
RAW_START = re.compile(r'r(#*)"')
CHAR = re.compile(r"'(\\u\{[0-9a-fA-F]+\}|\\.|[^\\'])'")
STRING_PATH = re.compile(r'"crate::[A-Za-z_][A-Za-z0-9_]*(::[A-Za-z0-9_<>, ]*)*"$')


def strip_comments_and_strings(text):
    """`text` with comments, string and char literals blanked out (newlines
    kept, so line numbers still hold)."""
    out = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            depth, j = 1, i + 2
            while j < n and depth:
                if text.startswith("/*", j):
                    depth, j = depth + 1, j + 2
                elif text.startswith("*/", j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "r" and RAW_START.match(text, i) and not _ident_before(text, i):
            hashes = len(RAW_START.match(text, i).group(1))
            end = text.find('"' + "#" * hashes, i + 2 + hashes)
            j = n if end < 0 else end + 1 + hashes
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            j = min(j + 1, n)
            literal = text[i:j]
            if STRING_PATH.match(literal):
                # A path in an attribute's string, as serde's
                # `deserialize_with = "crate::x::f"`: a real import.
                out.append(" " + literal[1:-1] + " ")
            else:
                out.append(re.sub(r"[^\n]", " ", literal))
            i = j
        elif c == "'":
            # A char literal ('a', '\n', '\u{1F}'), not a lifetime ('a).
            m = CHAR.match(text, i)
            if m:
                out.append(" " * len(m.group(0)))
                i += len(m.group(0))
            else:
                out.append(c)
                i += 1
        else:
            out.append(c)
            i += 1
    return "".join(out)


def _ident_before(text, i):
    return i > 0 and (text[i - 1].isalnum() or text[i - 1] == "_")


def _group_heads(text, start):
    """The first segment of each path in the `{...}` group at `start`
    (which is the `{`), and where the group ends."""
    heads, depth, i, expect = [], 0, start, False
    while i < len(text):
        c = text[i]
        if c == "{":
            depth += 1
            expect = depth == 1
        elif c == "}":
            depth -= 1
            if depth == 0:
                return heads, i + 1
        elif c == "," and depth == 1:
            expect = True
        elif expect and not c.isspace():
            m = IDENT.match(text, i)
            if m:
                heads.append((m.group(0), i))
                i = m.end()
                expect = False
                continue
            expect = False
        i += 1
    return heads, i


def references(text):
    """(module, offset) of every `crate::module` in Rust source `text`."""
    code = strip_comments_and_strings(text)
    found = []
    for m in PATH_START.finditer(code):
        if _ident_before(code, m.start()) or code[max(0, m.start() - 1)] == "$":
            continue
        rest = m.end()
        if rest < len(code) and code[rest] == "{":
            heads, _ = _group_heads(code, rest)
            found.extend(h for h in heads if h[0] not in ("self", "super"))
        else:
            ident = IDENT.match(code, rest)
            if ident:
                found.append((ident.group(0), m.start()))
    return found


def module_of(path, src):
    """The top-level module a file under `src` belongs to, or None for a
    crate root."""
    rel = os.path.relpath(path, src)
    parts = rel.split(os.sep)
    if len(parts) == 1:
        if parts[0] in ROOTS:
            return None
        return parts[0][:-3]
    if parts[0] == "bin":
        return None
    return parts[0]


def import_graph(src):
    """{module: {imported: [(file, line), ...]}} over the .rs files of `src`."""
    modules = set()
    for entry in os.listdir(src):
        full = os.path.join(src, entry)
        if os.path.isdir(full) and entry != "bin":
            modules.add(entry)
        elif entry.endswith(".rs") and entry not in ROOTS:
            modules.add(entry[:-3])
    graph = {m: {} for m in modules}
    for root, _, files in os.walk(src):
        for name in sorted(files):
            if not name.endswith(".rs"):
                continue
            path = os.path.join(root, name)
            owner = module_of(path, src)
            if owner is None:
                continue
            with open(path, encoding="utf-8") as f:
                text = f.read()
            for target, offset in references(text):
                if target == owner or target not in modules:
                    continue
                line = text.count("\n", 0, offset) + 1
                where = (os.path.relpath(path, os.path.dirname(src.rstrip(os.sep)) or "."), line)
                graph[owner].setdefault(target, []).append(where)
    return graph


def cycles(graph):
    """The strongly connected components of more than one module, each
    sorted, in sorted order (Tarjan's algorithm)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(tuple(sorted(component)))

    sys.setrecursionlimit(max(1000, 10 * len(graph)))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def read_allowed(path):
    """The cycles of the allow-list file (a missing file lists none)."""
    allowed = []
    if path is None or not os.path.exists(path):
        return allowed
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            members = line.split("#", 1)[0].split()
            if members:
                allowed.append((tuple(sorted(members)), number))
    return allowed


def describe(component, graph, limit=3):
    """The imports between the members of `component`, one arrow a line."""
    lines = []
    members = set(component)
    for a in component:
        for b in sorted(graph[a]):
            if b in members:
                sites = graph[a][b]
                shown = ", ".join(f"{f}:{n}" for f, n in sites[:limit])
                more = f" (+{len(sites) - limit} more)" if len(sites) > limit else ""
                lines.append(f"    {a} -> {b}: {shown}{more}")
    return lines


def _rel(path, src):
    return os.path.relpath(path, src).replace(os.sep, "/")


def room_report(src):
    """The circles of files as (members relative to `src`, lines
    describing the imports that close them)."""
    graph = file_graph(src)
    report = []
    for component in room_cycles(graph):
        members = set(component)
        lines = []
        for a in component:
            for b in sorted(graph[a]):
                if b in members:
                    shown = ", ".join(str(n) for n in graph[a][b][:4])
                    lines.append(f"    {_rel(a, src)} -> {_rel(b, src)} (line {shown})")
        report.append((tuple(sorted(_rel(f, src) for f in component)), lines))
    return report


def check(src, allow_path, out=sys.stdout):
    """Prints the verdict; returns the exit status."""
    graph = import_graph(src)
    found = cycles(graph)
    rooms = room_report(src)
    allowed = read_allowed(allow_path)
    allowed_sets = {members for members, _ in allowed}
    failed = False
    for component in found:
        listed = component in allowed_sets
        failed |= not listed
        head = "allowed cycle" if listed else "IMPORT CYCLE"
        print(f"{head} between {len(component)} modules: {' '.join(component)}", file=out)
        for line in describe(component, graph):
            print(line, file=out)
    for component, lines in rooms:
        listed = component in allowed_sets
        failed |= not listed
        head = "allowed circle" if listed else "CIRCLE OF FILES"
        print(f"{head} of {len(component)} files: {' '.join(component)}", file=out)
        for line in lines:
            print(line, file=out)
    found = found + [component for component, _ in rooms]
    for members, number in allowed:
        if members not in found:
            failed = True
            print(
                f"{allow_path}:{number}: the cycle {' '.join(members)} no longer exists: "
                "remove the line (or replace it with a cycle printed above)",
                file=out,
            )
    if failed:
        print(
            "floors: FAILED. Every import must point down the floors of "
            "docs/architecture.md, between folders and between the files of "
            "a folder (mod.rs on top of its files); break the cycle, do not list it.",
            file=out,
        )
        return 1
    if found:
        print(f"floors: ok, {len(found)} allowed cycle(s) still to break", file=out)
    else:
        print(
            f"floors: ok, no import cycle between the {len(graph)} top-level modules "
            f"nor between the {len(file_graph(src))} files",
            file=out,
        )
    return 0



# ---- Inside the folders: files on floors too --------------------------------

USE_START = re.compile(r"\buse\s+")
INLINE_PATH = re.compile(r"\b(crate|super|self)((?:\s*::\s*[A-Za-z_][A-Za-z0-9_]*)+)")
PUB_USE = re.compile(r"\bpub(?:\s*\([^)]*\))?\s+use\s+")


def module_files(src):
    """{module path (a tuple of names): file} for every .rs file of `src`;
    the crate root is ()."""
    mods = {}
    for root, _, files in os.walk(src):
        for name in sorted(files):
            if not name.endswith(".rs"):
                continue
            rel = os.path.relpath(os.path.join(root, name), src).split(os.sep)
            if rel[0] == "bin" or (len(rel) == 1 and rel[0] == "main.rs"):
                continue
            if len(rel) == 1 and rel[0] == "lib.rs":
                mods[()] = os.path.join(root, name)
                continue
            stem = rel[-1][:-3]
            path = tuple(rel[:-1]) if stem == "mod" else tuple(rel[:-1]) + (stem,)
            mods[path] = os.path.join(root, name)
    return mods


def _use_tree(code, i):
    """The paths (lists of names) of the use tree starting at `i`, and
    where it ends (after its `;`)."""
    paths, prefix_stack, current, n = [], [[]], [], len(code)
    while i < n:
        c = code[i]
        if c.isspace() or c == ":":
            i += 1
        elif c == "{":
            prefix_stack.append(prefix_stack[-1] + current)
            current = []
            i += 1
        elif c in ",}":
            if current:
                paths.append(prefix_stack[-1] + current)
            current = []
            if c == "}":
                prefix_stack.pop()
            i += 1
        elif c == ";":
            if current:
                paths.append(prefix_stack[-1] + current)
            return paths, i + 1
        elif c == "*":
            current.append("*")
            i += 1
        else:
            m = IDENT.match(code, i)
            if not m:
                i += 1
                continue
            word = m.group(0)
            i = m.end()
            if word == "as":
                # `x as y`: the alias is not part of the path.
                while i < n and code[i].isspace():
                    i += 1
                alias = IDENT.match(code, i)
                i = alias.end() if alias else i
                continue
            current.append(word)
    return paths, i


INLINE_MOD = re.compile(r"(#\[cfg\(test\)\]\s*)?\bmod\s+([A-Za-z_][A-Za-z0-9_]*)\s*\{")


def inline_modules(code):
    """[(start, end, name, test)] of the `mod name { ... }` blocks of
    `code` (comments and strings blanked), `test` for `#[cfg(test)]` ones."""
    blocks = []
    for m in INLINE_MOD.finditer(code):
        depth, i = 0, m.end() - 1
        while i < len(code):
            if code[i] == "{":
                depth += 1
            elif code[i] == "}":
                depth -= 1
                if depth == 0:
                    break
            i += 1
        blocks.append((m.start(), i, m.group(2), bool(m.group(1))))
    return blocks


def _enclosing(blocks, offset):
    """The inline module names around `offset`, outermost first, and
    whether one of them is a test module."""
    names, test = [], False
    for start, end, name, is_test in blocks:
        if start <= offset <= end:
            names.append(name)
            test |= is_test
    return names, test


def _absolute(segments, here, is_mod_file, children):
    """`segments` (a path written in module `here`) as an absolute module
    path, or None when it does not lead into this crate."""
    if not segments:
        return None
    head = segments[0]
    if head == "crate":
        return list(segments[1:])
    base = list(here)
    rest = list(segments)
    if head == "self":
        rest = rest[1:]
    elif head == "super":
        while rest and rest[0] == "super":
            if not base:
                return None
            base.pop()
            rest = rest[1:]
    elif head in children:
        # A child module named by itself (2018 paths).
        pass
    else:
        return None
    return base + rest


def _line_start(code, offset):
    return code.rfind("\n", 0, offset) + 1


def _defines(code, name):
    """Whether `code` defines an item called `name`."""
    return re.search(
        r"\b(struct|enum|fn|type|trait|const|static|mod|union|macro_rules!)\s+" + re.escape(name) + r"\b",
        code,
    ) is not None


def _resolve(path, mods, exports, codes, depth=0):
    """The module (a key of `mods`) that `path` names or holds an item
    of, through `pub use` re-exports (globs too)."""
    for cut in range(len(path), -1, -1):
        head = tuple(path[:cut])
        if head in mods:
            if cut < len(path) and depth < 8:
                names = exports.get(head, {})
                target = names.get(path[cut])
                if target is not None:
                    return _resolve(list(target) + list(path[cut + 1:]), mods, exports, codes, depth + 1)
                if not _defines(codes[head], path[cut]):
                    for glob in names.get("*", []):
                        inner = _resolve(list(glob) + [path[cut]], mods, exports, codes, depth + 1)
                        if inner is not None and _defines(codes[inner], path[cut]):
                            return inner
            return head
    return None


def file_graph(src):
    """{file: {imported file: [line, ...]}} over the .rs files of `src`,
    each path resolved to the file that defines what it names."""
    mods = module_files(src)
    children = {}
    for m in mods:
        if m:
            children.setdefault(m[:-1], set()).add(m[-1])
    codes = {}
    for m, path in mods.items():
        with open(path, encoding="utf-8") as f:
            codes[m] = strip_comments_and_strings(f.read())
    # `pub use` re-exports: {module: {name: absolute path}}.
    exports = {}
    for m, code in codes.items():
        for start in PUB_USE.finditer(code):
            paths, _ = _use_tree(code, start.end())
            for p in paths:
                absolute = _absolute(p, m, True, children.get(m, set()))
                if not absolute:
                    continue
                if p[-1] == "*":
                    exports.setdefault(m, {}).setdefault("*", []).append(absolute[:-1])
                else:
                    exports.setdefault(m, {})[p[-1]] = absolute
    graph = {}
    for m, code in codes.items():
        here = mods[m]
        edges = graph.setdefault(here, {})
        found = []
        handed_on = []
        for start in USE_START.finditer(code):
            if _ident_before(code, start.start()):
                continue
            paths, end = _use_tree(code, start.end())
            if PUB_USE.match(code, _line_start(code, start.start())):
                # A re-export hands names on: not an arrow of its own.
                handed_on.append((start.start(), end))
                continue
            found.extend((p, start.start()) for p in paths)
        for inline in INLINE_PATH.finditer(code):
            if _ident_before(code, inline.start()) or any(a <= inline.start() < b for a, b in handed_on):
                continue
            segments = [inline.group(1)] + re.findall(r"[A-Za-z_][A-Za-z0-9_]*", inline.group(2))
            found.append((segments, inline.start()))
        blocks = inline_modules(code)
        for segments, offset in found:
            inner, test = _enclosing(blocks, offset)
            if test:
                continue
            absolute = _absolute(segments, tuple(m) + tuple(inner), True, children.get(m, set()) if not inner else set())
            if absolute is None:
                continue
            target = _resolve([s for s in absolute if s != "*"], mods, exports, codes)
            if target is None or mods[target] == here or target == ():
                continue
            line = code.count("\n", 0, offset) + 1
            edges.setdefault(mods[target], set()).add(line)
    return {f: {t: sorted(lines) for t, lines in e.items()} for f, e in graph.items()}


def room_cycles(graph):
    """The circles of files: strongly connected components of more than
    one file, each sorted, in sorted order."""
    return cycles({f: set(e) for f, e in graph.items()})


PICTURE_BEGIN = "<!-- floors: drawn by scripts/check-floors.py --picture; checked by it -->"
PICTURE_END = "<!-- floors: end -->"


def floors_of(graph):
    """{module: floor}: 1 for a module that imports none of the others,
    else one above the highest it imports (a cycle's members share one)."""
    floor = {}

    def height(m, seen):
        if m in floor:
            return floor[m]
        if m in seen:
            return 0
        seen = seen | {m}
        floor[m] = 1 + max((height(t, seen) for t in graph[m]), default=0)
        return floor[m]

    for m in sorted(graph):
        height(m, frozenset())
    return floor


def picture(src):
    """The floors of the top-level modules as text, the top first, a
    folder with a slash; what each floor's modules import is below it."""
    graph = import_graph(src)
    floor = floors_of(graph)
    names = {m: m + "/" if os.path.isdir(os.path.join(src, m)) else m + ".rs" for m in graph}
    lines = []
    for level in range(max(floor.values(), default=0), 0, -1):
        members = sorted(names[m] for m in graph if floor[m] == level)
        row, rows = f"{level:>2} |", []
        for name in members:
            if len(row) + 1 + len(name) > 76:
                rows.append(row)
                row = "   |"
            row += " " + name
        rows.append(row)
        lines.extend(rows)
    return "\n".join(lines) + "\n"


def check_picture(src, doc, out=sys.stdout):
    """0 when `doc` holds the picture of `src`'s floors between its
    markers, 1 (saying how to redraw it) when it does not."""
    with open(doc, encoding="utf-8") as f:
        text = f.read()
    begin, end = text.find(PICTURE_BEGIN), text.find(PICTURE_END)
    want = "```text\n" + picture(src) + "```\n"
    if begin < 0 or end < begin:
        print(f"{doc}: no picture of the floors (markers {PICTURE_BEGIN!r} ... {PICTURE_END!r})", file=out)
        return 1
    held = text[begin + len(PICTURE_BEGIN):end].strip("\n") + "\n"
    if held != want:
        print(
            f"{doc}: the picture of the floors is not the code's: "
            "redraw it with scripts/check-floors.py --picture --write",
            file=out,
        )
        return 1
    return 0


def write_picture(src, doc):
    with open(doc, encoding="utf-8") as f:
        text = f.read()
    begin, end = text.find(PICTURE_BEGIN), text.find(PICTURE_END)
    if begin < 0 or end < begin:
        raise SystemExit(f"{doc}: no markers for the picture")
    drawn = PICTURE_BEGIN + "\n```text\n" + picture(src) + "```\n"
    with open(doc, "w", encoding="utf-8") as f:
        f.write(text[:begin] + drawn + text[end:])


def main(argv=None):
    here = os.path.dirname(os.path.abspath(__file__))
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--src", default=os.path.join(here, "..", "src"))
    parser.add_argument("--allow", default=os.path.join(here, "floors-allowed.txt"))
    parser.add_argument("--doc", default=os.path.join(here, "..", "docs", "architecture.md"))
    parser.add_argument("--picture", action="store_true", help="print the floors' picture")
    parser.add_argument("--write", action="store_true", help="with --picture: redraw it in --doc")
    args = parser.parse_args(argv)
    if not os.path.isdir(args.src):
        print(f"check-floors: no directory {args.src}", file=sys.stderr)
        return 2
    src = os.path.normpath(args.src)
    if args.picture:
        if args.write:
            write_picture(src, args.doc)
        else:
            sys.stdout.write(picture(src))
        return 0
    status = check(src, args.allow)
    if os.path.exists(args.doc):
        status |= check_picture(src, args.doc)
    return status


if __name__ == "__main__":
    sys.exit(main())
