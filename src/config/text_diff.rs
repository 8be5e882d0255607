//! The lines that differ between two versions of the configuration file:
//! what the console shows before an apply, what the audit log keeps of
//! it, and how a refused apply names the change another admin made. Pure:
//! texts in, hunks out.
//!
//! A longest common subsequence of lines, after the common head and tail
//! are set aside (an edit touches a few lines of a file of hundreds, so
//! what is left to compare is small); past [`MAX_CELLS`] the middle is
//! shown as removed and added whole rather than compared.

use serde::Serialize;
use utoipa::ToSchema;

/// Lines of context around each change.
pub const CONTEXT: usize = 3;

/// The largest middle (old lines times new lines) compared line by line.
pub const MAX_CELLS: usize = 4_000_000;

/// What a line of a hunk is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, ToSchema)]
#[serde(rename_all = "kebab-case")]
pub enum Op {
    /// In both texts (context).
    Same,
    /// Only in the old text.
    Removed,
    /// Only in the new text.
    Added,
}

/// One line of a hunk.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct DiffLine {
    /// Context, removed or added.
    pub op: Op,
    /// The line, without its end.
    pub text: String,
}

/// A run of changes with their context, as in a unified diff.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, ToSchema)]
pub struct Hunk {
    /// Its first line in the old text (1-based; the line before it when
    /// it removes nothing and has no context).
    pub old_start: usize,
    /// Its lines in the old text.
    pub old_lines: usize,
    /// Its first line in the new text (1-based).
    pub new_start: usize,
    /// Its lines in the new text.
    pub new_lines: usize,
    /// Its lines.
    pub lines: Vec<DiffLine>,
}

/// The hunks that turn `old` into `new`; empty when the texts' lines are
/// the same.
pub fn diff(old: &str, new: &str) -> Vec<Hunk> {
    let a: Vec<&str> = old.lines().collect();
    let b: Vec<&str> = new.lines().collect();
    hunks(&a, &b, &ops(&a, &b))
}

/// Each line of both texts in order: kept, removed or added.
fn ops(a: &[&str], b: &[&str]) -> Vec<Op> {
    let head = a.iter().zip(b).take_while(|(x, y)| x == y).count();
    let tail = a[head..]
        .iter()
        .rev()
        .zip(b[head..].iter().rev())
        .take_while(|(x, y)| x == y)
        .count();
    let (ma, mb) = (&a[head..a.len() - tail], &b[head..b.len() - tail]);
    let mut out = vec![Op::Same; head];
    if ma.len().saturating_mul(mb.len()) > MAX_CELLS {
        out.extend(std::iter::repeat_n(Op::Removed, ma.len()));
        out.extend(std::iter::repeat_n(Op::Added, mb.len()));
    } else {
        out.extend(middle(ma, mb));
    }
    out.extend(std::iter::repeat_n(Op::Same, tail));
    out
}

/// The longest common subsequence of `a` and `b`, walked from the start:
/// removals before additions where both are possible.
fn middle(a: &[&str], b: &[&str]) -> Vec<Op> {
    let (n, m) = (a.len(), b.len());
    // lcs[i][j]: the longest common subsequence of a[i..] and b[j..].
    let width = m + 1;
    let mut lcs = vec![0u32; (n + 1) * width];
    for i in (0..n).rev() {
        for j in (0..m).rev() {
            lcs[i * width + j] = if a[i] == b[j] {
                lcs[(i + 1) * width + j + 1] + 1
            } else {
                lcs[(i + 1) * width + j].max(lcs[i * width + j + 1])
            };
        }
    }
    let mut out = Vec::with_capacity(n + m);
    let (mut i, mut j) = (0, 0);
    while i < n || j < m {
        if i < n && j < m && a[i] == b[j] {
            out.push(Op::Same);
            i += 1;
            j += 1;
        } else if i < n && (j == m || lcs[(i + 1) * width + j] >= lcs[i * width + j + 1]) {
            out.push(Op::Removed);
            i += 1;
        } else {
            out.push(Op::Added);
            j += 1;
        }
    }
    out
}

/// The changes of `ops` grouped into hunks with [`CONTEXT`] lines around.
fn hunks(a: &[&str], b: &[&str], ops: &[Op]) -> Vec<Hunk> {
    // Each op with its line in a and in b (0-based, before the op).
    let mut at = Vec::with_capacity(ops.len());
    let (mut i, mut j) = (0, 0);
    for op in ops {
        at.push((i, j));
        match op {
            Op::Same => {
                i += 1;
                j += 1;
            }
            Op::Removed => i += 1,
            Op::Added => j += 1,
        }
    }
    let changed: Vec<usize> = (0..ops.len()).filter(|&k| ops[k] != Op::Same).collect();
    let mut out = Vec::new();
    let mut k = 0;
    while k < changed.len() {
        let first = changed[k];
        let mut last = first;
        // Changes closer than twice the context share a hunk.
        while k + 1 < changed.len() && changed[k + 1] - last <= 2 * CONTEXT + 1 {
            k += 1;
            last = changed[k];
        }
        k += 1;
        let from = first.saturating_sub(CONTEXT);
        let to = (last + CONTEXT + 1).min(ops.len());
        let mut hunk = Hunk {
            old_start: at[from].0 + 1,
            old_lines: 0,
            new_start: at[from].1 + 1,
            new_lines: 0,
            lines: Vec::with_capacity(to - from),
        };
        for (op, &(i, j)) in ops[from..to].iter().zip(&at[from..to]) {
            let text = match op {
                Op::Same | Op::Removed => a[i],
                Op::Added => b[j],
            };
            if *op != Op::Added {
                hunk.old_lines += 1;
            }
            if *op != Op::Removed {
                hunk.new_lines += 1;
            }
            hunk.lines.push(DiffLine {
                op: *op,
                text: text.to_string(),
            });
        }
        // As diff(1) numbers an empty side: the line before it.
        if hunk.old_lines == 0 {
            hunk.old_start -= 1;
        }
        if hunk.new_lines == 0 {
            hunk.new_start -= 1;
        }
        out.push(hunk);
    }
    out
}

/// The hunks as a unified diff (`@@ -12,4 +12,5 @@` and `-`, `+`, ` `
/// lines), as the audit log keeps it.
pub fn unified(hunks: &[Hunk]) -> String {
    let mut out = String::new();
    for h in hunks {
        out.push_str(&format!(
            "@@ -{},{} +{},{} @@\n",
            h.old_start, h.old_lines, h.new_start, h.new_lines
        ));
        for l in &h.lines {
            let mark = match l.op {
                Op::Same => ' ',
                Op::Removed => '-',
                Op::Added => '+',
            };
            out.push(mark);
            out.push_str(&l.text);
            out.push('\n');
        }
    }
    out
}

/// The changes in a few words, each hunk's lines in the new text: `line
/// 24: name = "lift" became name = "hoist"`, `lines 30-33 added`, `line 9
/// removed (port = "sim")`, `lines 12-14 changed`.
pub fn summary(hunks: &[Hunk]) -> String {
    let mut parts = Vec::new();
    for h in hunks {
        let mut line = h.new_start.max(1);
        let mut removed: Vec<&str> = Vec::new();
        let mut added: Vec<&str> = Vec::new();
        let mut first = None;
        for l in &h.lines {
            match l.op {
                Op::Same => line += 1,
                Op::Removed => {
                    first.get_or_insert(line);
                    removed.push(&l.text);
                }
                Op::Added => {
                    first.get_or_insert(line);
                    added.push(&l.text);
                    line += 1;
                }
            }
        }
        let at = first.unwrap_or(line);
        let span = |n: usize| {
            if n <= 1 {
                format!("line {at}")
            } else {
                format!("lines {at}-{}", at + n - 1)
            }
        };
        parts.push(match (removed.as_slice(), added.as_slice()) {
            ([old], [new]) => format!("line {at}: {} became {}", old.trim(), new.trim()),
            ([], new) => format!("{} added", span(new.len())),
            ([old], []) => format!("line {at} removed ({})", old.trim()),
            (old, []) => format!("{} lines removed at line {at}", old.len()),
            (_, new) => format!("{} changed", span(new.len())),
        });
    }
    parts.join("; ")
}

#[cfg(test)]
mod tests {
    use super::*;

    const OLD: &str = "# plant\n[[bus]]\nname = \"line1\"\nport = \"sim\"\n\n[[bus.drive]]\nunit = 1\nname = \"conveyor\"\n\n[[bus.drive]]\nunit = 2\nname = \"lift\"\n";

    #[test]
    fn one_line_changed_is_one_hunk_with_its_context() {
        let new = OLD.replace("name = \"lift\"", "name = \"hoist\"");
        let hunks = diff(OLD, &new);
        assert_eq!(hunks.len(), 1);
        let h = &hunks[0];
        assert_eq!(
            (h.old_start, h.old_lines, h.new_start, h.new_lines),
            (9, 4, 9, 4)
        );
        assert_eq!(
            unified(&hunks),
            "@@ -9,4 +9,4 @@\n \n [[bus.drive]]\n unit = 2\n-name = \"lift\"\n+name = \"hoist\"\n"
        );
        assert_eq!(
            summary(&hunks),
            "line 12: name = \"lift\" became name = \"hoist\""
        );
    }

    #[test]
    fn the_same_text_has_no_hunk() {
        assert!(diff(OLD, OLD).is_empty());
        assert_eq!(summary(&[]), "");
    }

    #[test]
    fn additions_and_removals_are_numbered_as_diff_numbers_them() {
        let added = format!("{OLD}\n[[bus.drive]]\nunit = 3\nname = \"press\"\n");
        let hunks = diff(OLD, &added);
        assert_eq!(hunks.len(), 1);
        let h = &hunks[0];
        assert_eq!(
            (h.old_start, h.old_lines, h.new_start, h.new_lines),
            (10, 3, 10, 7)
        );
        assert_eq!(summary(&hunks), "lines 13-16 added");
        // Removed at the top: the new side is empty before line 1.
        let hunks = diff("a\nb\nc\n", "b\nc\n");
        assert_eq!(unified(&hunks), "@@ -1,3 +1,2 @@\n-a\n b\n c\n");
        assert_eq!(summary(&hunks), "line 1 removed (a)");
        let hunks = diff("", "x\n");
        assert_eq!(unified(&hunks), "@@ -0,0 +1,1 @@\n+x\n");
    }

    #[test]
    fn changes_far_apart_are_separate_hunks_and_near_ones_share() {
        let lines: Vec<String> = (1..=30).map(|i| format!("k{i} = {i}")).collect();
        let old = lines.join("\n");
        let mut far = lines.clone();
        far[2] = "k3 = 0".into();
        far[25] = "k26 = 0".into();
        let hunks = diff(&old, &far.join("\n"));
        assert_eq!(hunks.len(), 2);
        assert_eq!(
            summary(&hunks),
            "line 3: k3 = 3 became k3 = 0; line 26: k26 = 26 became k26 = 0"
        );
        let mut near = lines;
        near[2] = "k3 = 0".into();
        near[8] = "k9 = 0".into();
        assert_eq!(diff(&old, &near.join("\n")).len(), 1);
    }

    #[test]
    fn every_line_is_accounted_for() {
        // Any texts: the old side of the hunks plus the untouched lines
        // give the old text, the new side the new one.
        let cases = [
            ("a\nb\nc\nd\n", "a\nx\nc\ny\nd\nz\n"),
            ("1\n2\n3\n", "3\n2\n1\n"),
            ("", ""),
            ("only\n", ""),
        ];
        for (old, new) in cases {
            let a: Vec<&str> = old.lines().collect();
            let b: Vec<&str> = new.lines().collect();
            let ops = ops(&a, &b);
            let kept_a = ops.iter().filter(|o| **o != Op::Added).count();
            let kept_b = ops.iter().filter(|o| **o != Op::Removed).count();
            assert_eq!((kept_a, kept_b), (a.len(), b.len()), "{old:?} -> {new:?}");
        }
    }
}
