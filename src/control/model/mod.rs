//! The model of the control core: a property-based state-machine test of
//! the rule every safety rule serves, "no motor moves without a live
//! owner", across random interleavings of what can happen to the core
//! (docs/safety.md, "The invariant, checked by a model").
//!
//! A case is a plant (`steps::Setup`: the stop actions, each session's
//! communication-loss time and action, which drives are active) and up to
//! [`steps::STEPS`] steps (`steps::Step`): writes from every face's client,
//! MQTT commands that did not come live, renewals, releases, sessions'
//! requests and ends, time passing, the bus held or its port down, drives
//! that fall silent or whose requests or replies are lost, and `kill -9`
//! with the journal left whole, torn, garbled, emptied, cut to its header
//! or deleted, then a start. `world` runs the real core (`Control`, its
//! write path, lease book and driver, brake guard, journal and restart)
//! with its clock turned by hand, on drives and a bus the `bench` serves;
//! the `oracle` keeps what the rules promise and checks the invariants
//! after every step.
//!
//! `DRIVEGATE_MODEL_CASES` sets the number of cases (default [`CASES`]),
//! `DRIVEGATE_MODEL_STEPS` the most steps of one; the suite draws the same
//! cases each run, `DRIVEGATE_MODEL_SEED=random` new ones; a failure prints
//! the seed, and `DRIVEGATE_MODEL_SEED` replays it (`DRIVEGATE_MODEL_TRACE=1`
//! prints what happens).

mod bench;
mod examples;
mod oracle;
mod steps;
mod world;

use std::time::Instant;

use proptest::test_runner::{Config, RngAlgorithm, TestCaseError, TestError, TestRng, TestRunner};

use steps::{Setup, Step};
use world::World;

/// Cases in the default run.
const CASES: u32 = 2000;

/// Runs one case: the plant of `setup`, then `steps`; the first invariant
/// broken, with the step that broke it.
fn run_case(setup: Setup, steps: &[Step]) -> Result<(), String> {
    run_case_then(setup, steps, |_| ())
}

/// [`run_case`], then `look` at the world as the steps left it.
fn run_case_then<R>(
    setup: Setup,
    steps: &[Step],
    look: impl FnOnce(&World) -> R,
) -> Result<R, String> {
    // The directory outlives the runtime: nothing of a case writes to it
    // once it is removed.
    let root = world::scratch()?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_time()
        .build()
        .map_err(|e| format!("no runtime: {e}"))?;
    let result = runtime.block_on(async {
        let mut world = World::new(setup, root.path())?;
        world.settle_start().await?;
        for (i, step) in steps.iter().enumerate() {
            if let Err(broken) = world.step(step).await {
                world.finish().await;
                return Err(format!("step {i} ({step:?}): {broken}"));
            }
        }
        let seen = look(&world);
        world.finish().await;
        Ok(seen)
    });
    drop(runtime);
    result
}

/// Hex digits of a seed.
const SEED_DIGITS: usize = 32;

/// The suite's seed: the same cases at every run, so a change that breaks
/// an invariant fails where it is made, not at a later run's draw. New
/// cases are `DRIVEGATE_MODEL_SEED=random`.
const SUITE_SEED: &str = "d71e6a7e0c5b4f1e9a2d3c8b7f605142";

/// The seed of this run: `DRIVEGATE_MODEL_SEED` ([`SEED_DIGITS`] hex
/// digits, or `random` for a new one), else [`SUITE_SEED`]. Cases are
/// drawn with XorShift: ChaCha's seeding of each case's generator cost a
/// sixth of the run in a debug build.
fn seed() -> Result<[u8; SEED_DIGITS / 2], String> {
    let mut seed = [0u8; SEED_DIGITS / 2];
    let given = std::env::var("DRIVEGATE_MODEL_SEED").unwrap_or_default();
    let hex = match given.trim() {
        "" => SUITE_SEED,
        "random" => {
            rand::fill(&mut seed);
            return Ok(seed);
        }
        hex => hex,
    };
    if hex.len() != SEED_DIGITS || !hex.is_ascii() {
        return Err(format!(
            "DRIVEGATE_MODEL_SEED is {SEED_DIGITS} hex digits (or random), not {hex:?}"
        ));
    }
    for (i, byte) in seed.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16)
            .map_err(|e| format!("DRIVEGATE_MODEL_SEED: {e}"))?;
    }
    Ok(seed)
}

#[test]
fn no_motor_moves_without_a_live_owner() {
    if let Err(e) = run_model() {
        panic!("{e}");
    }
}

fn run_model() -> Result<(), String> {
    let cases = match std::env::var("DRIVEGATE_MODEL_CASES") {
        Ok(v) => v
            .parse()
            .map_err(|e| format!("DRIVEGATE_MODEL_CASES: {e}"))?,
        Err(_) => CASES,
    };
    let seed = seed()?;
    let hex: String = seed.iter().map(|b| format!("{b:02x}")).collect();
    let mut config = Config::with_cases(cases);
    config.failure_persistence = None;
    let mut runner =
        TestRunner::new_with_rng(config, TestRng::from_seed(RngAlgorithm::XorShift, &seed));
    let started = Instant::now();
    let result = runner.run(&steps::case(), |(setup, steps)| {
        run_case(setup, &steps).map_err(TestCaseError::fail)
    });
    match result {
        Ok(()) => {
            eprintln!(
                "the model of the core: {cases} cases in {:.1} s (seed {hex})",
                started.elapsed().as_secs_f64()
            );
            Ok(())
        }
        Err(TestError::Fail(why, (setup, steps))) => Err(format!(
            "an invariant broke: {why}\n\nshrunk to {setup:?} and the steps\n{}\n\nreplay with DRIVEGATE_MODEL_SEED={hex}",
            steps
                .iter()
                .enumerate()
                .map(|(i, s)| format!("  {i}: {s:?}"))
                .collect::<Vec<_>>()
                .join("\n")
        )),
        Err(e) => Err(format!("{e} (seed {hex})")),
    }
}
