//! The `umbra` command: parses arguments and hands over to the library's CLI module.

fn main() {
    std::process::exit(umbra::cli::main());
}
