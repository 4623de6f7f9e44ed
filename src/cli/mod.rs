//! Subcommand groups of the `liquid-splat` binary.

pub mod case;
