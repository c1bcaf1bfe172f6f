//! The bake service (HTTP API, durable job queue, artifact store, workers) lands here
//! with its own issue; it will stay thin and call `engine::job::bake`. Nothing lives here
//! yet, deliberately: the engine and the command line come first.
