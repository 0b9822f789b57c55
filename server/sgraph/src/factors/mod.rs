//! The factors, one small file per family.

pub mod pose;
