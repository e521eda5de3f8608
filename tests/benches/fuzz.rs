//! `cargo bench -p roam-tests --bench fuzz`: a million inputs at every decoder (random
//! bytes, and valid encodings with bytes flipped, cut or extended; see
//! [`roam_tests::fuzz`]), which must each give a value or an error: no panic. A frame that
//! decodes goes on through the mesh decoder and the viewer's vertex builder. Prints one
//! JSON object. (`tests/tests/it/fuzz.rs` runs fewer under a counting allocator, to prove no
//! decode allocates beyond its limits.)
// A benchmark prints its figures (JSON), and shares helpers with the tests by path.
#![allow(unreachable_pub, clippy::print_stdout)]

use std::time::Instant;

use roam_tests::fuzz::Fuzz;

fn main() {
    const INPUTS: usize = 1_000_000;
    let mut fuzz = Fuzz::new(1);
    let (mut ok, mut err, mut panics) = (0u64, 0u64, 0u64);
    let mut first_panic: Option<Vec<u8>> = None;
    let mut input = Vec::new();
    let started = Instant::now();
    for n in 0..INPUTS {
        fuzz.input(n, &mut input);
        // Each stage runs under catch_unwind: a panic is counted (and the input kept),
        // not fatal, so the report's "panics" is what happened, not what was hoped.
        fuzz.feed(
            n,
            &input,
            &mut |_, bytes, step| match std::panic::catch_unwind(std::panic::AssertUnwindSafe(step))
            {
                Ok(value) => {
                    *if value { &mut ok } else { &mut err } += 1;
                    value
                }
                Err(_) => {
                    panics += 1;
                    first_panic.get_or_insert_with(|| bytes.to_vec());
                    false
                }
            },
        );
    }
    let secs = started.elapsed().as_secs_f64();
    println!(
        "{{\"inputs\":{INPUTS},\"decodes\":{},\"values\":{ok},\"errors\":{err},\"seconds\":{secs:.2},\"panics\":{panics}}}",
        ok + err + panics
    );
    if let Some(input) = first_panic {
        eprintln!("a decoder panicked, first on input {input:02x?}");
        std::process::exit(1);
    }
}
