//! The values of `hostsim run --seed/--set` and `hostsim sweep --seeds/--set` as a user
//! types them: the input, split at NUL bytes, is a `--seeds` value and `--set` values. Never
//! a panic or an allocation past the cap: `parse_seeds`, `Param::parse`, `count_runs`,
//! `expand` and `check` against the built-in square (plans of at most 8 runs), and `apply`
//! of the first run.
#![no_main]

use std::sync::OnceLock;

use hostsim::scenario::Scenario;
use hostsim::analysis::sweep::{self, Param};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let mut args = text.split('\0');
    let seeds = match sweep::parse_seeds(args.next().unwrap_or_default()) {
        Ok(s) => s,
        Err(e) => {
            let _ = std::format!("{e}");
            vec![1]
        }
    };
    assert!(seeds.len() as u64 <= sweep::MAX_RUNS);
    let params: Vec<Param> = args.filter_map(|a| Param::parse(a).ok()).collect();
    let Ok(count) = sweep::count_runs(seeds.len(), &params) else {
        return;
    };
    assert!(count <= sweep::MAX_RUNS);
    // Building and checking a million runs per input would be the fuzzer's time, not a
    // finding: the plan's count and cap are checked above for any size.
    if count > 8 {
        return;
    }
    let runs = sweep::expand(&seeds, &params).expect("counted within the cap");
    assert_eq!(runs.len() as u64, count);
    static BASE: OnceLock<Scenario> = OnceLock::new();
    let base = BASE.get_or_init(|| Scenario::builtin("square").expect("a built-in"));
    if sweep::check(base, &runs, &params).is_ok()
        && let Some(first) = runs.first()
    {
        let _ = sweep::apply(base, first.seed, &first.values);
    }
});
