//! The four arrow keys a driver holds, and the latch that turns key events into one state
//! per physics step.
//!
//! One latch serves both ends, for the same reason at each: a step (10 ms) sees every key
//! that was down at any moment since the step before. The viewer folds the window's key
//! events into the state it sends each step; the world folds the states it is sent into
//! the keys of a tick (one state a tick, or several at once when a backlog is caught up).
//! A press released before the step still acts in it, exactly once.

/// A set of arrow keys: bit 0 Up, 1 Down, 2 Left, 3 Right (the wire's [`KeyState`] bits).
///
/// [`KeyState`]: crate::messages::KeyState
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Keys(u8);

impl Keys {
    pub const NONE: Keys = Keys(0);
    pub const UP: Keys = Keys(1);
    pub const DOWN: Keys = Keys(2);
    pub const LEFT: Keys = Keys(4);
    pub const RIGHT: Keys = Keys(8);
    const ALL: u8 = 15;

    /// The keys of a bit pattern; `None` if bits other than the four keys' are set.
    pub fn from_bits(bits: u8) -> Option<Keys> {
        (bits & !Self::ALL == 0).then_some(Keys(bits))
    }

    pub fn bits(self) -> u8 {
        self.0
    }

    pub fn contains(self, other: Keys) -> bool {
        self.0 & other.0 == other.0
    }

    pub fn union(self, other: Keys) -> Keys {
        Keys(self.0 | other.0)
    }

    pub fn without(self, other: Keys) -> Keys {
        Keys(self.0 & !other.0)
    }

    pub fn is_empty(self) -> bool {
        self.0 == 0
    }
}

impl std::fmt::Display for Keys {
    /// `U`, `D`, `L`, `R` in that order, or `-` for none (the input script's notation).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.is_empty() {
            return f.write_str("-");
        }
        for (key, c) in [
            (Keys::UP, 'U'),
            (Keys::DOWN, 'D'),
            (Keys::LEFT, 'L'),
            (Keys::RIGHT, 'R'),
        ] {
            if self.contains(key) {
                write!(f, "{c}")?;
            }
        }
        Ok(())
    }
}

/// One step's keys: those held when the step was taken, and those pressed since the step
/// before (held or not now).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct KeyStep {
    pub held: Keys,
    pub pressed: Keys,
}

impl KeyStep {
    /// The keys that act in the step: held, or pressed at any moment since the last one.
    pub fn active(self) -> Keys {
        self.held.union(self.pressed)
    }
}

/// Keys between two steps: those held now, and those pressed since the last step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct KeyLatch {
    held: Keys,
    pressed: Keys,
}

impl KeyLatch {
    /// Keys go down.
    pub fn press(&mut self, keys: Keys) {
        self.held = self.held.union(keys);
        self.pressed = self.pressed.union(keys);
    }

    /// Keys come up (a press since the last step still counts).
    pub fn release(&mut self, keys: Keys) {
        self.held = self.held.without(keys);
    }

    /// The held keys become exactly `keys`: those not held before count as pressed.
    pub fn set_held(&mut self, keys: Keys) {
        self.pressed = self.pressed.union(keys.without(self.held));
        self.held = keys;
    }

    /// Folds in a step's state taken elsewhere (a viewer's [`KeyStep`]): its presses, then
    /// its held keys.
    pub fn apply(&mut self, step: KeyStep) {
        self.press(step.pressed);
        self.set_held(step.held);
    }

    /// This step's state, and a new step begins: a press, however short, is in exactly one
    /// step.
    pub fn take(&mut self) -> KeyStep {
        let step = KeyStep {
            held: self.held,
            pressed: self.pressed,
        };
        self.pressed = Keys::NONE;
        step
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bits_round_trip_and_foreign_bits_are_refused() {
        for bits in 0..16u8 {
            assert_eq!(Keys::from_bits(bits).map(Keys::bits), Some(bits));
        }
        for bits in 16..=255u8 {
            assert_eq!(Keys::from_bits(bits), None, "{bits:#x}");
        }
        assert_eq!(Keys::UP.union(Keys::LEFT).to_string(), "UL");
        assert_eq!(Keys::NONE.to_string(), "-");
    }

    #[test]
    fn a_short_press_is_in_exactly_one_step() {
        let mut l = KeyLatch::default();
        l.press(Keys::UP);
        l.release(Keys::UP);
        let s = l.take();
        assert_eq!(
            (s.held, s.pressed, s.active()),
            (Keys::NONE, Keys::UP, Keys::UP)
        );
        assert_eq!(l.take().active(), Keys::NONE);
    }

    #[test]
    fn set_held_counts_new_keys_as_pressed() {
        let mut l = KeyLatch::default();
        l.set_held(Keys::LEFT);
        assert_eq!(
            l.take(),
            KeyStep {
                held: Keys::LEFT,
                pressed: Keys::LEFT
            }
        );
        l.set_held(Keys::LEFT.union(Keys::UP));
        l.set_held(Keys::LEFT);
        assert_eq!(
            l.take(),
            KeyStep {
                held: Keys::LEFT,
                pressed: Keys::UP
            }
        );
        // Applying steps taken elsewhere folds them: both presses act in one step.
        l.apply(KeyStep {
            held: Keys::NONE,
            pressed: Keys::DOWN,
        });
        l.apply(KeyStep {
            held: Keys::RIGHT,
            pressed: Keys::RIGHT,
        });
        assert_eq!(l.take().active(), Keys::DOWN.union(Keys::RIGHT));
    }
}
