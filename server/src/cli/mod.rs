//! The binary's commands, one module per concern (data sets, tessellation, simulation,
//! serving), the terminal progress bar they share, and the data set opened for serving
//! that `serve`, `world`, `edge`, `bus-load` and `color-bench` share (`served`).

pub(crate) mod bus_load;
pub(crate) mod cluster;
pub(crate) mod color_bench;
pub(crate) mod data;
pub(crate) mod identity;
pub(crate) mod import;
pub(crate) mod net;
pub(crate) mod progress;
pub(crate) mod served;
pub(crate) mod sim;
pub(crate) mod tess;
pub(crate) mod token;
