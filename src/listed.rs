//! Enums that carry the list of their variants: [`listed_enum!`] declares
//! a fieldless enum and its `ALL`, made from the declaration itself, so a
//! new variant is in the list (and in every metric series, filter and
//! document made from it) without anyone remembering to add it.
//!
//! A leaf: any module, at any floor, may use it.

/// Declares a fieldless enum and `pub const ALL: [Self; N]`, every variant
/// in declaration order. Attributes and doc comments pass through:
///
/// ```
/// drivegate::listed::listed_enum! {
///     /// A colour.
///     #[derive(Debug, Clone, Copy, PartialEq, Eq)]
///     pub enum Colour {
///         /// Like blood.
///         Red,
///         /// Like grass.
///         Green,
///     }
/// }
/// assert_eq!(Colour::ALL, [Colour::Red, Colour::Green]);
/// ```
#[macro_export]
macro_rules! listed_enum {
    (
        $(#[$meta:meta])*
        $vis:vis enum $name:ident {
            $(
                $(#[$variant_meta:meta])*
                $variant:ident
            ),+ $(,)?
        }
    ) => {
        $(#[$meta])*
        $vis enum $name {
            $(
                $(#[$variant_meta])*
                $variant,
            )+
        }

        impl $name {
            /// Every variant, in declaration order (made from the
            /// declaration: none can be missing).
            pub const ALL: [$name; [$(stringify!($variant)),+].len()] = [$($name::$variant),+];
        }
    };
}

pub use crate::listed_enum;
