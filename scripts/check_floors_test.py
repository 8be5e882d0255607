#!/usr/bin/env python3
"""Tests of scripts/check-floors.py on small source trees made in a
temporary directory: `python3 scripts/check_floors_test.py` (scripts/test
runs it before the check itself)."""

import importlib.util
import io
import os
import tempfile
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
SPEC = importlib.util.spec_from_file_location("check_floors", os.path.join(HERE, "check-floors.py"))
floors = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(floors)


class Tree:
    """A src/ tree in a temporary directory, from {path: text}."""

    def __init__(self, files):
        self.dir = tempfile.TemporaryDirectory()
        self.src = os.path.join(self.dir.name, "src")
        for path, text in files.items():
            full = os.path.join(self.src, path)
            os.makedirs(os.path.dirname(full), exist_ok=True)
            with open(full, "w", encoding="utf-8") as f:
                f.write(text)
        self.allow = os.path.join(self.dir.name, "allowed.txt")

    def allowing(self, *lines):
        with open(self.allow, "w", encoding="utf-8") as f:
            f.write("# known cycles\n" + "".join(line + "\n" for line in lines))
        return self

    def run(self):
        out = io.StringIO()
        status = floors.check(self.src, self.allow, out)
        return status, out.getvalue()

    def cleanup(self):
        self.dir.cleanup()


# Floors: drive at the bottom, then bus, then monitor, then api on top.
ACYCLIC = {
    "lib.rs": "pub mod api;\npub mod bus;\npub mod drive;\npub mod monitor;\n",
    "drive/mod.rs": "pub struct Status;\n",
    "bus/mod.rs": "use crate::drive::Status;\npub mod origin;\n",
    "bus/origin.rs": "use super::*;\npub enum Origin {}\n",
    "monitor/mod.rs": "use crate::{bus::origin::Origin, drive::{self, Status}};\n",
    "api/mod.rs": "pub fn f() { crate::monitor::g(); let _ = crate::bus::X; }\n",
}


class CheckFloors(unittest.TestCase):
    def tree(self, files):
        tree = Tree(files)
        self.addCleanup(tree.cleanup)
        return tree

    def test_floors_without_a_cycle_pass(self):
        status, out = self.tree(ACYCLIC).run()
        self.assertEqual(status, 0, out)
        self.assertIn("no import cycle between the 4 top-level modules", out)

    def test_the_graph_reads_use_lines_groups_and_inline_paths(self):
        tree = self.tree(ACYCLIC)
        graph = floors.import_graph(tree.src)
        self.assertEqual(set(graph["monitor"]), {"bus", "drive"})
        self.assertEqual(set(graph["api"]), {"bus", "monitor"})
        self.assertEqual(set(graph["bus"]), {"drive"})
        self.assertEqual(graph["drive"], {})
        self.assertEqual(graph["api"]["monitor"], [("src/api/mod.rs", 1)])

    def test_a_cycle_fails_and_is_named_with_the_imports_that_close_it(self):
        files = dict(ACYCLIC)
        # The bus reaches up to the monitor: bus <-> monitor.
        files["bus/tap.rs"] = "\n\nuse crate::monitor::Ring;\n"
        status, out = self.tree(files).run()
        self.assertEqual(status, 1, out)
        self.assertIn("IMPORT CYCLE between 2 modules: bus monitor", out)
        self.assertIn("bus -> monitor: src/bus/tap.rs:3", out)
        self.assertIn("monitor -> bus: src/monitor/mod.rs:1", out)
        self.assertNotIn("api", out.split("IMPORT CYCLE")[1].split("floors:")[0])

    def test_a_cycle_through_a_nested_group_or_a_serde_path_counts(self):
        files = dict(ACYCLIC)
        files["drive/units.rs"] = (
            "use crate::{\n    bus::{\n        self,\n    },\n};\n"
        )
        status, out = self.tree(files).run()
        self.assertEqual(status, 1, out)
        self.assertIn("IMPORT CYCLE between 2 modules: bus drive", out)
        files = dict(ACYCLIC)
        files["drive/units.rs"] = '#[serde(deserialize_with = "crate::api::parse")]\n'
        status, out = self.tree(files).run()
        self.assertEqual(status, 1, out)
        self.assertIn("api bus drive monitor", out)

    def test_comments_strings_and_macro_paths_are_not_imports(self):
        files = dict(ACYCLIC)
        files["drive/doc.rs"] = (
            "//! See [`crate::api`].\n"
            "/* crate::monitor::x /* nested */ crate::bus */\n"
            'const S: &str = "use crate::api::f; http://x";\n'
            "const C: char = '\"';\n"
            "macro_rules! m { () => { $crate::api::f() } }\n"
            "fn lifetime<'a>(x: &'a str) -> &'a str { x }\n"
        )
        status, out = self.tree(files).run()
        self.assertEqual(status, 0, out)

    def test_an_allowed_cycle_passes_while_it_exists(self):
        files = dict(ACYCLIC)
        files["bus/tap.rs"] = "use crate::monitor::Ring;\n"
        status, out = self.tree(files).allowing("monitor bus").run()
        self.assertEqual(status, 0, out)
        self.assertIn("allowed cycle between 2 modules: bus monitor", out)

    def test_a_cycle_that_grew_beyond_its_allowed_line_fails(self):
        files = dict(ACYCLIC)
        files["bus/tap.rs"] = "use crate::monitor::Ring;\n"
        files["drive/more.rs"] = "use crate::bus::Origin;\n"
        status, out = self.tree(files).allowing("bus monitor").run()
        self.assertEqual(status, 1, out)
        self.assertIn("IMPORT CYCLE between 3 modules: bus drive monitor", out)
        self.assertIn("the cycle bus monitor no longer exists", out)

    def test_an_allowed_cycle_that_is_gone_fails_so_the_list_shrinks(self):
        status, out = self.tree(ACYCLIC).allowing("bus monitor").run()
        self.assertEqual(status, 1, out)
        self.assertIn("allowed.txt:2: the cycle bus monitor no longer exists", out)

    def test_files_of_a_folder_in_a_circle_fail_with_the_lines_that_close_it(self):
        files = dict(ACYCLIC)
        files["bus/mod.rs"] = "pub mod origin;\npub mod queue;\n"
        files["bus/origin.rs"] = "use super::queue::Job;\npub enum Origin {}\n"
        files["bus/queue.rs"] = "\nuse crate::bus::origin::Origin;\npub struct Job;\n"
        status, out = self.tree(files).run()
        self.assertEqual(status, 1, out)
        self.assertIn("CIRCLE OF FILES of 2 files: bus/origin.rs bus/queue.rs", out)
        self.assertIn("bus/origin.rs -> bus/queue.rs (line 1)", out)
        self.assertIn("bus/queue.rs -> bus/origin.rs (line 2)", out)

    def test_mod_rs_stands_on_top_of_its_files_and_re_exports_are_no_arrows(self):
        files = dict(ACYCLIC)
        files["bus/mod.rs"] = (
            "mod origin;\nmod types;\npub use origin::Origin;\npub use types::*;\n"
            "use origin::make;\npub fn run() { make(); }\n"
        )
        # The file takes a type of its sibling through mod.rs's glob: an
        # arrow to types.rs, not up to mod.rs.
        files["bus/origin.rs"] = "use super::Job;\npub enum Origin {}\npub fn make() {}\n"
        files["bus/types.rs"] = "pub struct Job;\n"
        tree = self.tree(files)
        status, out = tree.run()
        self.assertEqual(status, 0, out)
        graph = floors.file_graph(tree.src)
        origin = os.path.join(tree.src, "bus", "origin.rs")
        self.assertEqual(set(graph[origin]), {os.path.join(tree.src, "bus", "types.rs")})
        # A file that takes what mod.rs defines while mod.rs uses it: a circle.
        files["bus/origin.rs"] = "use super::run;\npub enum Origin {}\npub fn make() {}\n"
        status, out = self.tree(files).run()
        self.assertEqual(status, 1, out)
        self.assertIn("CIRCLE OF FILES of 2 files: bus/mod.rs bus/origin.rs", out)

    def test_a_test_module_s_imports_and_inline_modules_resolve_where_they_stand(self):
        files = dict(ACYCLIC)
        files["bus/mod.rs"] = "pub mod origin;\npub mod queue;\n"
        files["bus/queue.rs"] = "use super::origin::Origin;\npub struct Job;\n"
        files["bus/origin.rs"] = (
            "pub enum Origin {}\n"
            "#[cfg(test)]\nmod tests {\n    use super::*;\n    use crate::bus::queue::Job;\n}\n"
            "mod inner {\n    use super::Origin;\n}\n"
        )
        tree = self.tree(files)
        status, out = tree.run()
        self.assertEqual(status, 0, out)
        self.assertEqual(floors.file_graph(tree.src)[os.path.join(tree.src, "bus", "origin.rs")], {})

    def test_the_picture_puts_each_module_one_floor_above_what_it_imports(self):
        tree = self.tree(ACYCLIC)
        self.assertEqual(
            floors.picture(tree.src),
            " 4 | api/\n 3 | monitor/\n 2 | bus/\n 1 | drive/\n",
        )
        doc = os.path.join(tree.dir.name, "architecture.md")
        with open(doc, "w", encoding="utf-8") as f:
            f.write(f"# Floors\n{floors.PICTURE_BEGIN}\n```text\n 1 | drive/\n```\n{floors.PICTURE_END}\nmore\n")
        out = io.StringIO()
        self.assertEqual(floors.check_picture(tree.src, doc, out), 1)
        self.assertIn("not the code's: redraw it with scripts/check-floors.py --picture --write", out.getvalue())
        floors.write_picture(tree.src, doc)
        self.assertEqual(floors.check_picture(tree.src, doc, io.StringIO()), 0)
        with open(doc, encoding="utf-8") as f:
            self.assertTrue(f.read().endswith(f"{floors.PICTURE_END}\nmore\n"))

    def test_the_architecture_doc_holds_the_code_s_picture(self):
        out = io.StringIO()
        status = floors.check_picture(
            os.path.join(HERE, "..", "src"), os.path.join(HERE, "..", "docs", "architecture.md"), out
        )
        self.assertEqual(status, 0, out.getvalue())

    def test_the_repository_passes_with_its_allow_list(self):
        status = floors.check(
            os.path.join(HERE, "..", "src"),
            os.path.join(HERE, "floors-allowed.txt"),
            io.StringIO(),
        )
        self.assertEqual(status, 0)


if __name__ == "__main__":
    unittest.main()
