//! "Did you mean": the known name closest to a mistyped one (`conveyr` ->
//! `conveyor`, `11520` -> `115200`), so a refusal can offer the right
//! spelling beside the list of what exists.
//!
//! A leaf: any module, at any floor, may use it.

/// The name of `known` closest to `given`, if one is close enough to be a
/// slip of the keyboard: at most one edit (a letter added, dropped,
/// changed, or two swapped) per three letters, and at least one. Case is
/// ignored; an exact match is no suggestion.
pub(crate) fn closest<'a>(
    given: &str,
    known: impl IntoIterator<Item = &'a str>,
) -> Option<&'a str> {
    let given_lower = given.to_lowercase();
    let limit = (given.chars().count() / 3).max(1);
    known
        .into_iter()
        .filter(|k| *k != given)
        .map(|k| (edits(&given_lower, &k.to_lowercase()), k))
        .filter(|(d, _)| *d <= limit)
        .min_by_key(|(d, _)| *d)
        .map(|(_, k)| k)
}

/// Edits from `a` to `b`: insertions, deletions, substitutions and swaps
/// of neighbours (the optimal string alignment distance).
fn edits(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    // d[i][j]: edits from a[..i] to b[..j].
    let mut d = vec![vec![0usize; b.len() + 1]; a.len() + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    for (j, cell) in d[0].iter_mut().enumerate() {
        *cell = j;
    }
    for i in 1..=a.len() {
        for j in 1..=b.len() {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut best = (d[i - 1][j] + 1)
                .min(d[i][j - 1] + 1)
                .min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                best = best.min(d[i - 2][j - 2] + 1);
            }
            d[i][j] = best;
        }
    }
    d[a.len()][b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    const DRIVES: [&str; 4] = ["conveyor", "lift", "turntable", "feeder"];

    #[test]
    fn slips_of_the_keyboard_are_found() {
        assert_eq!(closest("conveyr", DRIVES), Some("conveyor"));
        assert_eq!(closest("Conveyor", DRIVES), Some("conveyor"));
        assert_eq!(closest("lfit", DRIVES), Some("lift"));
        assert_eq!(closest("feeders", DRIVES), Some("feeder"));
        assert_eq!(
            closest("11520", ["9600", "115200", "57600"]),
            Some("115200")
        );
    }

    #[test]
    fn other_names_are_no_suggestion() {
        assert_eq!(closest("press", DRIVES), None);
        assert_eq!(closest("x", DRIVES), None);
        assert_eq!(closest("conveyor", DRIVES), None);
    }

    #[test]
    fn edits_are_counted() {
        assert_eq!(edits("", "abc"), 3);
        assert_eq!(edits("abc", "acb"), 1);
        assert_eq!(edits("kitten", "sitting"), 3);
    }
}
