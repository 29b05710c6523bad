//! The processor features this build was compiled for, checked at start-up: on x86-64,
//! `.cargo/config.toml` enables AVX2, F16C (half-precision conversions) and POPCNT (bit
//! counts), which every AVX2 processor has, and a processor without it would otherwise stop at the
//! first such instruction with an illegal-instruction signal instead of a message.

/// `Err` saying what to do when the processor lacks an instruction set this build uses.
pub fn check() -> Result<(), String> {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if !has_avx2() {
        return Err(
            "this build of biscale uses AVX2, F16C and POPCNT instructions (enabled in \
                    .cargo/config.toml) and this processor does not have them; rebuild for \
                    any x86-64 processor with RUSTFLAGS=\"-C target-cpu=x86-64\" cargo build \
                    --release"
                .into(),
        );
    }
    Ok(())
}

/// Whether the processor has AVX2, F16C and POPCNT and the operating system saves the 256-bit registers,
/// asked of the processor itself (`is_x86_feature_detected!` answers `true` without asking
/// when the build enables the feature).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(never)]
fn has_avx2() -> bool {
    use std::arch::x86_64::{__cpuid, __cpuid_count};
    // `cpuid` exists on every x86-64 processor.
    let max = __cpuid(0).eax;
    let l1 = __cpuid(1);
    let (osxsave, avx) = (l1.ecx & (1 << 27) != 0, l1.ecx & (1 << 28) != 0);
    let (f16c, popcnt) = (l1.ecx & (1 << 29) != 0, l1.ecx & (1 << 23) != 0);
    if max < 7 || !osxsave || !avx || !f16c || !popcnt {
        return false;
    }
    let xcr0: u32;
    // SAFETY: `xgetbv` with ecx = 0 is defined when OSXSAVE is set (checked above); it reads a
    // register and touches no memory.
    unsafe {
        std::arch::asm!("xgetbv", in("ecx") 0u32, out("eax") xcr0, out("edx") _,
                        options(nomem, nostack, preserves_flags));
    }
    // XMM and YMM state enabled by the operating system, and the AVX2 bit of leaf 7.
    xcr0 & 0b110 == 0b110 && __cpuid_count(7, 0).ebx & (1 << 5) != 0
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_processor_running_the_tests_has_what_the_build_uses() {
        // The tests run on the machine they were built for.
        assert_eq!(super::check(), Ok(()));
    }
}
