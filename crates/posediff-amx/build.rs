//! Sets `cfg(amx_host)` when the machine that builds the tests has AMX tiles (the CPU's
//! `amx_tile` and `amx_bf16` flags in /proc/cpuinfo, and `POSEDIFF_NO_AMX` unset), so that the
//! tests that need the tiles are reported as skipped (ignored) elsewhere instead of passing
//! without running. The library itself decides at run time (`available()`).

include!("../host_cpu_cfg.rs");

fn main() {
    host_cpu_cfg("amx_host", &["amx_tile", "amx_bf16"], "POSEDIFF_NO_AMX");
}
