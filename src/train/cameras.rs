//! Which training view each iteration uses.
//!
//! Upstream keeps a stack of the training cameras; each iteration removes one
//! at a uniformly random position, and the stack is refilled when it is empty.
//! So every pass visits each camera exactly once, in random order. Here the
//! choice comes from the run's seeded generator; the state (remaining stack and
//! generator) is saved in checkpoints so a resumed run continues identically.

use crate::math::Rng;

#[derive(Clone, Debug, PartialEq)]
/// The stack of training cameras of upstream, drawn from with a seeded generator.
pub struct CameraSampler {
    count: usize,
    stack: Vec<usize>,
    rng: Rng,
}

/// One pick: the camera index and how many cameras were left in the pass
/// before it was taken (upstream's AST noise scales with 1 / that number).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pick {
    /// The camera index.
    pub index: usize,
    /// Cameras left in the pass before this one was taken.
    pub remaining: usize,
}

impl CameraSampler {
    /// A sampler of `count` cameras, seeded by the run seed `seed`.
    pub fn new(count: usize, seed: u64) -> Self {
        CameraSampler {
            count,
            stack: Vec::new(),
            rng: Rng::stream(seed, 0x00CA_3E0A),
        }
    }

    /// Restore from saved state.
    pub fn from_state(count: usize, stack: Vec<usize>, rng_state: u64) -> Self {
        CameraSampler {
            count,
            stack,
            rng: Rng::new(rng_state),
        }
    }

    /// Number of training cameras.
    pub fn count(&self) -> usize {
        self.count
    }

    /// The cameras left in the current pass, in stack order.
    pub fn stack(&self) -> &[usize] {
        &self.stack
    }

    /// The state of the sampler's generator.
    pub fn rng_state(&self) -> u64 {
        self.rng.state()
    }

    /// The next camera. Panics only if constructed with zero cameras, which
    /// the trainer rejects before.
    pub fn draw(&mut self) -> Pick {
        if self.stack.is_empty() {
            self.stack = (0..self.count).collect();
        }
        let remaining = self.stack.len();
        let k = self.rng.below(remaining as u64) as usize;
        Pick {
            index: self.stack.remove(k),
            remaining,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_pass_visits_every_camera_once() {
        let mut s = CameraSampler::new(7, 3);
        for _ in 0..3 {
            let mut seen: Vec<usize> = (0..7).map(|_| s.draw().index).collect();
            seen.sort();
            assert_eq!(seen, (0..7).collect::<Vec<_>>());
        }
    }

    #[test]
    fn restored_sampler_continues_identically() {
        let mut a = CameraSampler::new(5, 11);
        a.draw();
        a.draw();
        let mut b = CameraSampler::from_state(5, a.stack().to_vec(), a.rng_state());
        for _ in 0..12 {
            assert_eq!(a.draw(), b.draw());
        }
    }

    #[test]
    fn remaining_counts_down_within_a_pass() {
        let mut s = CameraSampler::new(4, 0);
        let r: Vec<usize> = (0..5).map(|_| s.draw().remaining).collect();
        assert_eq!(r, vec![4, 3, 2, 1, 4]);
    }
}
