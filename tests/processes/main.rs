//! The real `photostereo` binary as a child process: the command line, crash recovery,
//! hostile clients, the memory budget and strict inputs, one module each. What they
//! measure (memory, timings) is the child's. The connection tests, which must run alone,
//! are in the `serial` program.

#[path = "../binserver/mod.rs"]
mod binserver;
#[path = "../common/mod.rs"]
mod common;
#[path = "../seed/mod.rs"]
mod seed;

mod budget;
mod cli;
mod crash;
mod hostile;
mod integrate_cli;
mod strict_inputs;
