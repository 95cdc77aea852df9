//! Stereo rectification (being written).
