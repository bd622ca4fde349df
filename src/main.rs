//! The `procl` command line.
fn main() {}
