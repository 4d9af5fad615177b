//! What was being done when an error happened, kept in the library's own typed error: a crate
//! whose error enum has a `Context { context: String, source: Box<Self> }` variant gets a
//! `Context` trait for its results from [`error_context!`](crate::error_context).

/// Defines a `Context` trait adding what was being done to every `Result` whose error converts
/// into `$error` (which needs a `Context { context, source }` variant).
#[macro_export]
macro_rules! error_context {
    ($error:ident) => {
        /// Adds what was being done to an error.
        pub trait Context<T> {
            /// Wraps the error, converted into this crate's error, with `f()`.
            fn context_with(self, f: impl FnOnce() -> String) -> Result<T, $error>;
        }

        impl<T, E: Into<$error>> Context<T> for Result<T, E> {
            fn context_with(self, f: impl FnOnce() -> String) -> Result<T, $error> {
                self.map_err(|e| $error::Context {
                    context: f(),
                    source: Box::new(e.into()),
                })
            }
        }
    };
}
