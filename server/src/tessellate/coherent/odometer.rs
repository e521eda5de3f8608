//! The odometers a kept evaluation falls due against ([`Odometer`]): how far the eye has
//! travelled and turned, in fixed-point keys for the schedules.

/// An odometer (how far the eye has travelled, world units, or turned, radians, summed
/// over the frames), and the keys its schedules are kept in: readings in fixed point
/// (`SCALE` steps a unit) from a base, rounded down, so a member is evaluated no later
/// than its reading (at most one step early). Before the keys of the reading now pass
/// 2^31, the base moves up to it and every key shifts down (a few times a day of driving
/// or turning, if ever: 2^31 steps are 524 km, or 2,048 radians).
#[derive(Clone, Copy)]
pub(super) struct Odometer {
    pub(super) reading: f64,
    pub(super) base: f64,
    pub(super) scale: f64,
}

impl Odometer {
    pub(super) fn new(scale: f64) -> Odometer {
        Odometer {
            reading: 0.0,
            base: 0.0,
            scale,
        }
    }

    /// The key of reading `at` (saturating: a key too large is due early, never late).
    #[inline]
    fn key_of(&self, at: f64) -> u32 {
        ((at - self.base) * self.scale).floor() as u32
    }

    /// The key of the reading now.
    pub(super) fn now(&self) -> u32 {
        self.key_of(self.reading)
    }

    /// The key at which an evaluation with this `slack` falls due (`None`: never).
    #[inline]
    pub(super) fn key(&self, slack: f32) -> Option<u32> {
        slack
            .is_finite()
            .then(|| self.key_of(self.reading + f64::from(slack)))
    }

    /// Moves the base to the reading now once its key passes 2^31: the shift of the keys.
    pub(super) fn rebase(&mut self) -> Option<u32> {
        let shift = self.now();
        (shift >= 1 << 31).then(|| {
            self.base += f64::from(shift) / self.scale;
            shift
        })
    }
}

/// Steps per world unit of the travel odometer, per radian of the turn odometer.
pub(super) const TRAVEL_SCALE: f64 = 4096.0;
pub(super) const TURN_SCALE: f64 = 1048576.0;

#[cfg(test)]
mod tests {
    use super::*;

    /// A rebase shifts every key by what it says, exactly, and leaves the odometer's
    /// key now near 0.
    #[test]
    fn odometer_rebase_shifts_keys() {
        let mut o = Odometer::new(TRAVEL_SCALE);
        o.reading = 600_000.0;
        let before: Vec<u32> = [0.0, 0.001, 5.5, 1e4]
            .map(|s| o.key(s).expect("finite"))
            .into();
        let shift = o.rebase().expect("600 km is past 2^31 steps");
        let after: Vec<u32> = [0.0, 0.001, 5.5, 1e4]
            .map(|s| o.key(s).expect("finite"))
            .into();
        for (b, a) in before.iter().zip(&after) {
            assert_eq!(b - shift, *a);
        }
        assert_eq!((o.now(), o.rebase()), (0, None));
        assert_eq!(o.key(f32::INFINITY), None, "exact: never due");
    }
}
