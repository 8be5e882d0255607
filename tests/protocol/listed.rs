//! `listed_enum!` as another crate uses it, by its exported path (the
//! example of its documentation; the library's examples are not compiled
//! as doctests, which cost a build of their own on every run).

drivegate::listed::listed_enum! {
    /// A colour.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum Colour {
        /// Like blood.
        Red,
        /// Like grass.
        Green,
    }
}

#[test]
fn a_listed_enum_lists_its_variants_in_declaration_order() {
    assert_eq!(Colour::ALL, [Colour::Red, Colour::Green]);
    assert_eq!(Colour::ALL.len(), 2);
}
