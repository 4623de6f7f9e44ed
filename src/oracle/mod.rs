pub mod deform;
