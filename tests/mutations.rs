//! Seeded mutation testing of everything umbra reads from a user, in every `cargo test` (the
//! coverage-guided fuzzing is `cargo fuzz` on the targets in `fuzz/`, docs/design.md): the
//! scene reader on hundreds of mutated `scene.json`s of the independent fixture, the schedule
//! parser on mutated default schedules and the image decoders on mutated PNGs. None may panic;
//! a refused scene names `scene.json`.

mod common;

use common::TempDir;
use std::panic::{catch_unwind, AssertUnwindSafe};
use umbra::random::Stream;

/// One random edit of `bytes`: flip a byte, delete or duplicate a span, or write a digit,
/// quote, bracket or huge number at a random place.
fn mutate(bytes: &[u8], stream: &mut Stream) -> Vec<u8> {
    let mut out = bytes.to_vec();
    if out.is_empty() {
        return out;
    }
    let at = stream.below(out.len());
    match stream.below(6) {
        0 => out[at] ^= 1 << stream.below(8),
        1 => {
            let end = (at + 1 + stream.below(16)).min(out.len());
            out.drain(at..end);
        }
        2 => {
            let end = (at + 1 + stream.below(16)).min(out.len());
            let span = out[at..end].to_vec();
            out.splice(at..at, span);
        }
        3 => out.splice(at..at, b"1e39".iter().copied()).for_each(drop),
        4 => out[at] = b"\"[]{}:,-0.9"[stream.below(11)],
        _ => out.splice(at..at, b"-0".iter().copied()).for_each(drop),
    }
    out
}

#[test]
fn mutated_scenes_are_refused_or_loaded_never_a_panic() {
    let dir = TempDir::new("mutated-scene");
    let source = common::example_scene();
    // The fixture's files, copied once; only scene.json is mutated.
    let mut stack = vec![source.clone()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap().flatten() {
            let path = entry.path();
            let target = dir.path().join(path.strip_prefix(&source).unwrap());
            if path.is_dir() {
                std::fs::create_dir_all(&target).unwrap();
                stack.push(path);
            } else {
                std::fs::copy(&path, &target).unwrap();
            }
        }
    }
    let original = std::fs::read(source.join("scene.json")).unwrap();
    let mut stream = Stream::new(7, 0xF022, 0);
    let (mut refused, mut loaded) = (0, 0);
    for _ in 0..400 {
        let mut text = original.clone();
        for _ in 0..1 + stream.below(3) {
            text = mutate(&text, &mut stream);
        }
        std::fs::write(dir.path().join("scene.json"), &text).unwrap();
        let result = catch_unwind(AssertUnwindSafe(|| umbra::scene::Scene::load(dir.path())));
        match result {
            Err(_) => panic!("the scene reader panicked on:\n{}", String::from_utf8_lossy(&text)),
            Ok(Err(e)) => {
                assert!(e.to_string().contains("scene.json"), "{e}");
                refused += 1;
            }
            Ok(Ok(_)) => loaded += 1,
        }
    }
    assert!(refused > 200, "most mutations break the scene: {refused} refused, {loaded} loaded");
}

#[test]
fn mutated_schedules_and_images_never_panic() {
    let mut stream = Stream::new(8, 0xF022, 0);
    let schedule = umbra::schedule::DEFAULT_TEXT.as_bytes();
    for _ in 0..1000 {
        let text = mutate(schedule, &mut stream);
        let text = String::from_utf8_lossy(&text).into_owned();
        let result = catch_unwind(|| umbra::schedule::Schedule::parse(&text, std::path::Path::new("m.toml")).map(|_| ()));
        assert!(result.is_ok(), "the schedule parser panicked on:\n{text}");
    }
    let dir = TempDir::new("mutated-png");
    let png = std::fs::read(common::example_scene().join("images/c00_f0000_sun.png")).unwrap();
    let path = dir.path().join("m.png");
    for _ in 0..300 {
        let bytes = mutate(&png, &mut stream);
        std::fs::write(&path, &bytes).unwrap();
        assert!(catch_unwind(|| umbra::imageio::read_rgb(&path).map(|_| ())).is_ok(), "the PNG decoder panicked");
        assert!(catch_unwind(|| umbra::imageio::read_mask(&path).map(|_| ())).is_ok(), "the mask decoder panicked");
        assert!(catch_unwind(|| umbra::imageio::dimensions(&path).map(|_| ())).is_ok(), "the header reader panicked");
    }
}
