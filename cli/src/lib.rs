//! The `stitch` command's library part: what it reads from users' files, shared with the
//! fuzz targets (`fuzz/`). The command itself is `src/main.rs`.

pub mod inputs;
