//! Subcommands of the `isrf` binary: argument structs (clap) and thin `run`
//! functions that call the library.

pub mod bench;
pub mod bench_splats;
pub mod demo;
pub mod edit;
pub mod eval;
pub mod features;
pub mod fuzz;
pub mod import;
pub mod info;
pub mod render;
pub mod run;
pub mod segment;
pub mod splats;
pub mod teacher;
pub mod train;
