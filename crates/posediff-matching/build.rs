//! Sets `cfg(vnni_host)` when the machine that builds the tests has AVX-512 VNNI (the CPU's
//! `avx512f`, `avx512bw` and `avx512_vnni` flags in /proc/cpuinfo, and `POSEDIFF_NO_VNNI`
//! unset), so that the test of the byte kernel is reported as skipped (ignored) elsewhere
//! instead of passing without running. The library itself decides at run time.

fn main() {
    println!("cargo::rustc-check-cfg=cfg(vnni_host)");
    println!("cargo::rerun-if-env-changed=POSEDIFF_NO_VNNI");
    println!("cargo::rerun-if-changed=build.rs");
    let flags = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let has = |flag: &str| {
        flags
            .lines()
            .filter(|l| l.starts_with("flags"))
            .any(|l| l.split_whitespace().any(|f| f == flag))
    };
    if has("avx512f")
        && has("avx512bw")
        && has("avx512_vnni")
        && std::env::var_os("POSEDIFF_NO_VNNI").is_none()
    {
        println!("cargo::rustc-cfg=vnni_host");
    }
}
