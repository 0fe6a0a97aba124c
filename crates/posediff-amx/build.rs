//! Sets `cfg(amx_host)` when the machine that builds the tests has AMX tiles (the CPU's
//! `amx_tile` and `amx_bf16` flags in /proc/cpuinfo, and `POSEDIFF_NO_AMX` unset), so that the
//! tests that need the tiles are reported as skipped (ignored) elsewhere instead of passing
//! without running. The library itself decides at run time (`available()`).

fn main() {
    println!("cargo::rustc-check-cfg=cfg(amx_host)");
    println!("cargo::rerun-if-env-changed=POSEDIFF_NO_AMX");
    println!("cargo::rerun-if-changed=build.rs");
    let flags = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let has = |flag: &str| {
        flags
            .lines()
            .filter(|l| l.starts_with("flags"))
            .any(|l| l.split_whitespace().any(|f| f == flag))
    };
    if has("amx_tile") && has("amx_bf16") && std::env::var_os("POSEDIFF_NO_AMX").is_none() {
        println!("cargo::rustc-cfg=amx_host");
    }
}
