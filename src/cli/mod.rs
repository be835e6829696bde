//! Subcommands of the `isrf` binary: argument structs (clap) and thin `run`
//! functions that call the library.

pub mod bench;
pub mod demo;
pub mod edit;
pub mod eval;
pub mod fuzz;
pub mod info;
pub mod render;
pub mod run;
pub mod segment;
pub mod train;
