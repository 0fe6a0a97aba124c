// Shared by the build scripts of the crates whose tests need a CPU feature (`include!`d, so
// it is not a crate of its own): the tests that cannot run on the building machine are then
// reported as skipped (ignored) instead of passing without running. The libraries decide at
// run time.

/// Declares `cfg(<cfg>)` and sets it when this machine's CPU has every flag of `flags` (as
/// /proc/cpuinfo names them) and the environment variable `off` is unset.
fn host_cpu_cfg(cfg: &str, flags: &[&str], off: &str) {
    println!("cargo::rustc-check-cfg=cfg({cfg})");
    println!("cargo::rerun-if-env-changed={off}");
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed=../host_cpu_cfg.rs");
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let has = |flag: &str| {
        cpuinfo
            .lines()
            .filter(|l| l.starts_with("flags"))
            .any(|l| l.split_whitespace().any(|f| f == flag))
    };
    if flags.iter().all(|f| has(f)) && std::env::var_os(off).is_none() {
        println!("cargo::rustc-cfg={cfg}");
    }
}
