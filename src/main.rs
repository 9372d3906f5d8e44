//! The `umbra` command: tunes the C allocator for umbra's work, parses arguments and hands over
//! to the library's CLI module.

fn main() {
    keep_freed_memory();
    std::process::exit(umbra::cli::main());
}

/// A training step and a view's trace allocate and free tensors of megabytes many times over.
/// glibc serves blocks of 128 KiB or more by `mmap` and returns them at `free`, and trims its
/// heap's top whenever 128 KiB of it are free, so the kernel maps and zeroes those pages again
/// at the next step: on `human-sun` a quarter of a fit's CPU time was the kernel's (7.6 s of
/// 28.8 over 150 iterations), 0.3 s with blocks up to 32 MiB (glibc's most) served from the
/// heap and the heap never trimmed. Either alone made it worse (15.4 and 21.6 s). The memory a
/// step frees is reused by the next one, so the peak grows by little.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_freed_memory() {
    // glibc's <malloc.h>: M_TRIM_THRESHOLD -1, M_MMAP_THRESHOLD -3.
    extern "C" {
        fn mallopt(param: i32, value: i32) -> i32;
    }
    // SAFETY: mallopt only sets allocator parameters; called before any thread starts.
    unsafe {
        mallopt(-3, 32 << 20);
        mallopt(-1, i32::MAX);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_freed_memory() {}
