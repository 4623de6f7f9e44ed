pub mod rasterize;
