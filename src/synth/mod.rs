//! Honest synthetic scenes (being written).
