//! `cargo bench --bench shadows`: the shadow-casting benchmark (same code as `umbra bench shadows`).

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    match umbra::bench::shadows(std::path::Path::new("runs/bench"), quick) {
        Ok(table) => print!("{table}"),
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
}
