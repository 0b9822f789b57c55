//! The `vsgraphs-eval` command's parts that need the server: whole scenarios run through its
//! pipeline and scored (see [`scenario`]). The scores themselves are the `vsgraphs-eval`
//! library's.

pub mod scenario;
