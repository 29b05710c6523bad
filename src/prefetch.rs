//! Software prefetch hints: ask the processor to start loading memory that a loop will read
//! shortly, so that the load's latency overlaps the work in between. The re-rank of a search
//! reads small blocks of thousands of library records that are in no cache
//! ([`crate::lightlobes::LightLobes::fbar`]); there the hardware's own prefetchers, which
//! follow strides, do not help.

/// Bytes per cache line on the processors this build targets.
pub const LINE: usize = 64;

/// Hint that `data` will be read soon: one prefetch per cache line it spans. Only a hint: it
/// changes no value and never faults; on targets without one it does nothing.
#[inline]
pub fn read<T>(data: &[T]) {
    #[cfg(target_arch = "x86_64")]
    {
        let start = data.as_ptr() as usize;
        let end = start + std::mem::size_of_val(data);
        let mut line = start & !(LINE - 1);
        while line < end {
            // SAFETY: `prefetcht0` is a hint available on every x86-64 processor (SSE); it
            // never faults and reads nothing into the program's state, whatever the address.
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    line as *const i8,
                );
            }
            line += LINE;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = data;
}

#[cfg(test)]
mod tests {
    #[test]
    fn prefetching_changes_nothing_and_accepts_any_slice() {
        let v: Vec<f32> = (0..1000).map(|i| i as f32).collect();
        super::read(&v);
        super::read(&v[3..17]);
        super::read::<f32>(&[]);
        assert_eq!(v[999], 999.0);
    }
}
