//! Deterministic mutation replay over the fuzz seed corpus: every seed
//! (`case new` for each stage, the committed fixture datasets) is mutated a
//! fixed number of times by a seeded generator (bit flips, byte and
//! integer substitutions, truncations, splices, digits of metadata numbers
//! replaced by huge ones) and run through the same entry points as the
//! `cargo fuzz` targets (`liquid_splat::fuzz`). Any panic fails the test;
//! an abort or hang fails the run. Longer, coverage-guided runs: see
//! `fuzz/README.md`.

mod support;

use liquid_splat::fuzz::{self, Outcome};
use liquid_splat::math::Rng;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use support::tmp;

const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures");
/// Mutations per seed (`LIQUID_SPLAT_FUZZ_MUTATIONS` overrides it for a
/// longer replay; `LIQUID_SPLAT_FUZZ_SEED` changes the generator's seed).
const MUTATIONS: usize = 150;

fn env_or(key: &str, default: u64) -> u64 {
    std::env::var(key)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Values that break parsers: boundaries of the integer types, huge and
/// non-finite numbers as text.
const TOKENS: [&str; 12] = [
    "18446744073709551615",
    "4611686018427387904",
    "1000000000000",
    "65536",
    "0",
    "-1",
    "NaN",
    "inf",
    "1e308",
    "-0",
    "4294967296",
    "",
];

fn mutate(seed: &[u8], r: &mut Rng) -> Vec<u8> {
    let mut v = seed.to_vec();
    let pick = |r: &mut Rng, n: usize| (r.uniform() * n as f64) as usize % n.max(1);
    let rounds = 1 + pick(r, 3);
    for _ in 0..rounds {
        if v.is_empty() {
            v.push(0);
        }
        match pick(r, 7) {
            0 => {
                let i = pick(r, v.len());
                v[i] ^= 1 << pick(r, 8);
            }
            1 => {
                let i = pick(r, v.len());
                v[i] = [0u8, 0xff, 0x7f, 0x80, b'9', b'-', b'"', b'\n'][pick(r, 8)];
            }
            2 => {
                let n = pick(r, v.len() + 1);
                v.truncate(n);
            }
            3 => {
                // An 8-byte little-endian integer (safetensors header
                // length and offsets) overwritten with a boundary value.
                let i = pick(r, v.len());
                let x = [u64::MAX, 1 << 62, 0, 1 << 32, 16][pick(r, 5)].to_le_bytes();
                for (k, b) in x.iter().enumerate() {
                    if i + k < v.len() {
                        v[i + k] = *b;
                    }
                }
            }
            4 => {
                // A run of digits (a number in JSON, PLY or metadata text)
                // replaced by a token.
                let starts: Vec<usize> = (0..v.len())
                    .filter(|&i| v[i].is_ascii_digit() && (i == 0 || !v[i - 1].is_ascii_digit()))
                    .collect();
                if !starts.is_empty() {
                    let s = starts[pick(r, starts.len())];
                    let mut e = s;
                    while e < v.len() && (v[e].is_ascii_digit() || v[e] == b'.') {
                        e += 1;
                    }
                    let t = TOKENS[pick(r, TOKENS.len())].as_bytes();
                    v.splice(s..e, t.iter().copied());
                }
            }
            5 => {
                // Duplicate a slice (repeated keys, elements, frames).
                let a = pick(r, v.len());
                let b = (a + 1 + pick(r, 64)).min(v.len());
                let chunk = v[a..b].to_vec();
                let at = pick(r, v.len());
                v.splice(at..at, chunk);
            }
            _ => {
                let a = pick(r, v.len());
                let b = (a + 1 + pick(r, 16)).min(v.len());
                v.drain(a..b);
            }
        }
    }
    v
}

fn replay(name: &str, seeds: &[Vec<u8>], run: &dyn Fn(&[u8]) -> Outcome) {
    let mut r = Rng::new(env_or("LIQUID_SPLAT_FUZZ_SEED", 0x5eed));
    let mutations = env_or("LIQUID_SPLAT_FUZZ_MUTATIONS", MUTATIONS as u64) as usize;
    for (k, seed) in seeds.iter().enumerate() {
        assert_eq!(
            run(seed),
            Outcome::Accepted,
            "{name}: seed {k} is not accepted"
        );
        let mut counts = [0usize; 3];
        for m in 0..mutations {
            let input = mutate(seed, &mut r);
            let outcome = catch_unwind(AssertUnwindSafe(|| run(&input)))
                .unwrap_or_else(|_| panic!("{name}: seed {k} mutation {m} panicked"));
            counts[outcome as usize] += 1;
        }
        // The mutations reach past the first check: some are refused, and
        // some still read (a mutation that only breaks the container would
        // test nothing else).
        assert!(
            counts[1] > 0,
            "{name}: seed {k}: nothing refused {counts:?}"
        );
        eprintln!("{name} seed {k}: accepted / refused / over budget = {counts:?}");
    }
}

/// Small `case new` files of every stage (the `cargo fuzz` corpus is made
/// the same way, see fuzz/seed-corpus.sh).
fn case_seeds(dir: &Path) -> Vec<Vec<u8>> {
    let mut seeds = Vec::new();
    let runs: [&[&str]; 7] = [
        &[
            "rasterize",
            "--width",
            "16",
            "--height",
            "12",
            "--count",
            "6",
        ],
        &[
            "rasterize",
            "--dtype",
            "f32",
            "--width",
            "16",
            "--height",
            "12",
            "--count",
            "6",
            "--gradient",
            "inria",
        ],
        &["deform", "--count", "5"],
        &[
            "deform", "--dtype", "f32", "--field", "mlp", "--count", "5", "--6dof",
        ],
        &["loss", "--width", "12", "--height", "11"],
        &["step", "--width", "16", "--height", "12", "--count", "6"],
        &[
            "step", "--dtype", "f32", "--width", "16", "--height", "12", "--count", "6", "--field",
            "mlp",
        ],
    ];
    for (k, a) in runs.iter().enumerate() {
        let p = dir.join(format!("seed{k}.safetensors"));
        let mut args = vec!["liquid-splat", "case", "new", a[0], p.to_str().unwrap()];
        args.extend(&a[1..]);
        assert_eq!(liquid_splat::cli::run(args), 0, "case new {a:?}");
        seeds.push(std::fs::read(&p).unwrap());
    }
    seeds
}

#[test]
fn mutated_case_files_never_panic() {
    let dir = tmp("cases");
    replay("case file", &case_seeds(&dir), &fuzz::case_file);
}

#[test]
fn mutated_datasets_never_panic() {
    let dir = tmp("datasets");
    let fuzzer = fuzz::DatasetFuzzer::new(&dir.join("work"), Path::new(FIXTURES)).unwrap();
    let seeds = fuzz::dataset_seeds(Path::new(FIXTURES)).unwrap();
    replay("dataset", &seeds, &|d| fuzzer.run(d));
}
