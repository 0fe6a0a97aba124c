//! Sets `cfg(vnni_host)` when the machine that builds the tests has AVX-512 VNNI (the CPU's
//! `avx512f`, `avx512bw` and `avx512_vnni` flags in /proc/cpuinfo, and `POSEDIFF_NO_VNNI`
//! unset), so that the test of the byte kernel is reported as skipped (ignored) elsewhere
//! instead of passing without running. The library itself decides at run time.

include!("../host_cpu_cfg.rs");

fn main() {
    host_cpu_cfg(
        "vnni_host",
        &["avx512f", "avx512bw", "avx512_vnni"],
        "POSEDIFF_NO_VNNI",
    );
}
