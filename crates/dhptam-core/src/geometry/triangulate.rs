//! Triangulation (being written).
