//! Numeric kernels shared by the stages: the dense matrix products
//! ([`matmul`]) and the fast-math functions ([`fastmath`]) of the
//! deformation fields, the rasterizer and LPIPS.
//!
//! Each kernel is compiled for several instruction sets (AVX-512, AVX2 and
//! the build target's baseline) and picks one at run time
//! ([`fastmath::isa`], which tests and benchmarks can pin with
//! [`fastmath::force_isa`]). Every path gives the same bits, on every CPU
//! and for any thread count: the kernels fix the order of every sum and use
//! only correctly rounded or exact operations, so the instruction set only
//! changes speed.
//!
//! [`vec_written_by`] and [`par_blocks_written`] build output vectors that
//! are written once, in place, without being zeroed first (zeroing cost as
//! much as a tenth of a matrix product). `prefetch` asks for values a
//! stage will read soon (a hint; it changes no value).

pub mod fastmath;
pub mod matmul;

use rayon::prelude::*;
use std::mem::MaybeUninit;

/// A vector of `len` values written in place by `write`, never zeroed
/// first.
///
/// `write` receives the `len` uninitialised slots and returns them written,
/// as an initialised slice of the same memory: code can only hold such a
/// slice once every value in it has been written (for example the one
/// [`par_blocks_written`] returns, or a block that a matrix product
/// returns). Panics when the returned slice is not the whole buffer.
pub fn vec_written_by<T>(
    len: usize,
    write: impl FnOnce(&mut [MaybeUninit<T>]) -> &mut [T],
) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(len);
    let buf = &mut v.spare_capacity_mut()[..len];
    let start = buf.as_ptr() as *const T;
    let written = write(buf);
    assert!(
        written.len() == len && (len == 0 || std::ptr::eq(written.as_ptr(), start)),
        "vec_written_by: the writer returned another slice than its buffer"
    );
    // SAFETY: `written` is an initialised `&mut [T]` over exactly the first
    // `len` slots of the capacity (checked above; nothing to initialise when
    // `len` is 0), so those are initialised.
    unsafe { v.set_len(len) };
    v
}

/// `buf` written in parallel blocks of `block` values: `write(i, dst, side)`
/// receives block `i` (uninitialised; the last one may be shorter) with the
/// matching block of `side_block` values of `side`, and returns the block
/// written, as an initialised slice of the same memory (checked: panics
/// otherwise). Every block is visited exactly once; a single block runs on
/// the calling thread. Returns the whole buffer, initialised.
pub fn par_blocks_written<'a, T, S, F>(
    buf: &'a mut [MaybeUninit<T>],
    block: usize,
    side: &mut [S],
    side_block: usize,
    write: F,
) -> &'a mut [T]
where
    T: Send,
    S: Send,
    F: for<'b> Fn(usize, &'b mut [MaybeUninit<T>], &mut [S]) -> &'b mut [T] + Sync,
{
    let block = block.max(1);
    let blocks = buf.len().div_ceil(block);
    assert!(
        side_block == 0 || side.len().div_ceil(side_block) >= blocks,
        "par_blocks_written: side has fewer blocks than the buffer"
    );
    let check = |i: usize, dst: &mut [MaybeUninit<T>], sb: &mut [S]| {
        let (start, len) = (dst.as_ptr() as *const T, dst.len());
        let written = write(i, dst, sb);
        assert!(
            std::ptr::eq(written.as_ptr(), start) && written.len() == len,
            "par_blocks_written: a writer returned another slice than its block"
        );
    };
    if blocks <= 1 {
        if blocks == 1 {
            let end = side_block.min(side.len());
            check(0, buf, &mut side[..end]);
        }
    } else if side_block == 0 {
        buf.par_chunks_mut(block)
            .enumerate()
            .for_each(|(i, dst)| check(i, dst, &mut []));
    } else {
        buf.par_chunks_mut(block)
            .zip(side.par_chunks_mut(side_block))
            .enumerate()
            .for_each(|(i, (dst, sb))| check(i, dst, sb));
    }
    // SAFETY: every block of `buf` (the chunks partition it, and each was
    // visited once above) was returned as an initialised `&mut [T]` over
    // its own memory (checked), so every value of `buf` is initialised.
    unsafe { &mut *(buf as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// `hint(p)` for one address `p` in each 64-byte line that the `len` values
/// of `v` from `start` span (clipped to `v`): the first byte of the range,
/// then the first byte of each later line the range reaches, all inside
/// `v`.
#[inline(always)]
fn each_line<T>(v: &[T], start: usize, len: usize, mut hint: impl FnMut(*const u8)) {
    let end = (start.saturating_add(len)).min(v.len());
    if start >= end {
        return;
    }
    let size = std::mem::size_of::<T>();
    let base = v.as_ptr() as *const u8;
    let (first, stop) = (start * size, end * size);
    hint(base.wrapping_add(first));
    // The offset of the next line's first byte: `base` need not be on a
    // line's start.
    let mut b = first + 64 - (base as usize + first) % 64;
    while b < stop {
        hint(base.wrapping_add(b));
        b += 64;
    }
}

/// Ask the CPU to bring `len` values of `v` from `start` into its caches
/// (one hint per 64-byte line they span); only a hint, clipped to `v`.
#[inline(always)]
pub(crate) fn prefetch<T>(v: &[T], start: usize, len: usize) {
    #[cfg(target_arch = "x86_64")]
    each_line(v, start, len, |p| {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: `p` is a byte inside `v` (`each_line`); a prefetch never
        // faults and changes no value.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(p as *const i8) }
    });
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (v, start, len);
}

/// Ask the CPU to bring `len` values of `v` from `start` into its caches
/// for writing (`prefetchw`, one per 64-byte line they span), so that lines
/// another core holds are taken over before the stores reach them; only a
/// hint, clipped to `v`.
#[inline(always)]
pub(crate) fn prefetch_write<T>(v: &[T], start: usize, len: usize) {
    each_line(v, start, len, prefetch_write_at);
}

/// Ask the CPU to bring the line of address `p` into its caches for
/// writing (`prefetchw`); only a hint, which changes no value. Callers pass
/// addresses inside their buffers. Every x86-64 CPU runs the instruction:
/// AMD's have had it since their first x86-64 ones, Intel's since
/// Broadwell (the PRFCHW feature), and earlier Intel ones execute its
/// encoding as a no-op.
#[inline(always)]
// The pointer is only a hint's address: nothing is read or written there.
#[allow(clippy::pointers_in_nomem_asm_block)]
pub(crate) fn prefetch_write_at(p: *const u8) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads no value, writes none and does not fault on
    // any address; to the program it is a no-op (`nomem`).
    unsafe {
        std::arch::asm!("prefetchw [{0}]", in(reg) p, options(nostack, preserves_flags, nomem));
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Ask the CPU to bring the value `v[i]` into its caches: the lines of its
/// first and last bytes (one line or two); only a hint, nothing when `i` is
/// outside `v`.
#[inline(always)]
pub(crate) fn prefetch_value<T>(v: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        if i >= v.len() {
            return;
        }
        let size = std::mem::size_of::<T>();
        let first = v.as_ptr().wrapping_add(i) as *const i8;
        // SAFETY: `i < v.len()`, so bytes `first .. first + size` lie in
        // `v`; a prefetch never faults and changes no value.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(first);
            _mm_prefetch::<_MM_HINT_T0>(first.add(size.max(1) - 1));
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (v, i);
}

/// `s` with every slot set to `v`, as the initialised slice of the same
/// memory (for a writer of [`vec_written_by`] or [`par_blocks_written`]
/// that starts from a constant).
pub(crate) fn filled<T: Copy>(s: &mut [MaybeUninit<T>], v: T) -> &mut [T] {
    for x in s.iter_mut() {
        x.write(v);
    }
    // SAFETY: every slot was written just above, and `MaybeUninit<T>` has
    // the layout of `T`.
    unsafe { &mut *(s as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// An initialised slice as slots to overwrite.
///
/// # Safety
/// Only initialised values may be written through the result (no
/// `MaybeUninit::uninit()`), so that `v` holds valid values again when the
/// borrow ends.
pub(crate) unsafe fn as_slots<T>(v: &mut [T]) -> &mut [MaybeUninit<T>] {
    // SAFETY: `MaybeUninit<T>` has the layout of `T`; the caller writes only
    // initialised values.
    unsafe { &mut *(v as *mut [T] as *mut [MaybeUninit<T>]) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_line_hints_every_line_a_range_spans_once_inside_it() {
        let v = vec![0u8; 400];
        let (lo, hi) = (v.as_ptr() as usize, v.as_ptr() as usize + v.len());
        for start in 0..140 {
            for len in 0..200 {
                let mut got = Vec::new();
                each_line(&v, start, len, |p| got.push(p as usize));
                let end = (start + len).min(v.len());
                let want: Vec<usize> = if start >= end {
                    Vec::new()
                } else {
                    ((lo + start) / 64..=(lo + end - 1) / 64).collect()
                };
                let lines: Vec<usize> = got.iter().map(|p| p / 64).collect();
                assert_eq!(lines, want, "start {start}, len {len}");
                assert!(
                    got.iter().all(|&p| p >= lo + start && p < hi),
                    "start {start}, len {len}"
                );
            }
        }
    }

    #[test]
    fn blocks_are_written_in_place_once_each() {
        let mut side = vec![0usize; 10];
        let v: Vec<u32> = vec_written_by(23, |buf| {
            par_blocks_written(buf, 5, &mut side, 2, |i, dst, sb| {
                sb.iter_mut().for_each(|s| *s += 1);
                let n = dst.len();
                for (j, d) in dst.iter_mut().enumerate() {
                    d.write((i * 5 + j) as u32);
                }
                // SAFETY: the loop above wrote all n values.
                let out = unsafe { &mut *(dst as *mut [MaybeUninit<u32>] as *mut [u32]) };
                assert_eq!(out.len(), n);
                out
            })
        });
        assert_eq!(v, (0..23).collect::<Vec<u32>>());
        // 5 blocks, each with its own 2 side values; the rest untouched.
        assert_eq!(side, [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]);
    }

    #[test]
    #[should_panic(expected = "another slice")]
    fn a_slice_other_than_the_buffer_is_refused() {
        let _ = vec_written_by::<f32>(4, |_| {
            // A different, initialised slice of the right length.
            Box::leak(Box::new([1.0f32; 4])).as_mut_slice()
        });
    }
}
