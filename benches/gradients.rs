//! `cargo bench --bench gradients`: SDF gradients by forward-mode tangents vs central
//! differences (same code as `umbra bench gradients`).

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let scene = std::path::Path::new(umbra::bench::DEFAULT_SCENE);
    match umbra::bench::gradients(std::path::Path::new("runs/bench"), quick, Some(scene)) {
        Ok(table) => print!("{table}"),
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
}
