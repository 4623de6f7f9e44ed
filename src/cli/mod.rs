//! Subcommand groups of the `liquid-splat` binary: argument parsing and
//! messages only; the work is done by the library.

pub mod bench;
pub mod case;
pub mod count;
pub mod data;
pub mod experiment;
pub mod gradcheck;
pub mod train;
