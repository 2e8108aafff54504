//! # coilscope-core
//!
//! The physics core of coilscope: parameter sets, the nonlinear electrodynamic transducer
//! model, its normal form, the integrator and the excitation signals.
//!
//! ## Conventions (from `docs/formats.md`)
//!
//! * SI units everywhere: metres, seconds, volts, amperes, ohms, henries, kilograms, newtons,
//!   kelvin (temperatures are rises above ambient).
//! * x > 0 is "coil out", away from the back plate.
//! * Kms(x) is the secant stiffness: the suspension's restoring force is `Kms(x) x`.
//! * Power series are ascending in x (metres): `f(x) = sum_j c_j x^j`.
//! * The reluctance force is `+1/2 L'(x) i^2`; with it the model conserves energy.
//!
//! ## Where things are
//!
//! * [`params`]: parameter sets, validation, the embedded real drivers.
//! * [`model`]: the model's equations — the one place they are written.
//! * [`normal_form`]: the seed paper's normal form `x''' = f(z) + g(z) u` (Eqs. 5-9).
//! * [`integrate`]: band-limited input interpolation and RK4 sub-stepping.
//! * [`simulate`](mod@simulate): the virtual transducer driven by a sampled voltage.
//! * [`small_signal`]: the linearised model at rest: impedance, Thiele/Small figures.
//! * [`effects`]: which of a real driver's effects (creep, LR-3, Le(i), Rms(v)) a set has.
//! * [`enclosure`]: the box the driver works into (closed, vented, passive radiator).
//! * [`creep`]: LOG creep of the suspension as a bank of Maxwell elements.
//! * [`population`]: physically plausible drivers drawn from a seed, microspeakers to
//!   subwoofers, for judging the tool on drivers it was not developed on.
//! * [`limits`]: displacement limits XBl, XC, XL, Xsym, Ak over a reached range.
//! * [`recent`]: a few values kept by key (the chain's FFT-sized vectors in a fit).
//! * [`result`]: the identification result file, typed.
//! * [`excitation`]: seeded test signals (IEC 60268-1 noise, pink noise, sine, multitone,
//!   sweep) and named RNGs.

pub mod chain;
pub mod creep;
pub mod effects;
pub mod enclosure;
pub mod excitation;
pub mod fft;
pub mod integrate;
pub mod inverse;
pub mod jet;
pub mod limits;
pub mod mass;
pub mod model;
pub mod normal_form;
pub mod params;
pub mod poly;
pub mod population;
pub mod production;
pub mod recent;
pub mod result;
pub mod schema;
pub mod simulate;
pub mod small_signal;

pub use model::{Model, State};
pub use params::{embedded_driver, embedded_driver_names, ParamError, Parameters};
pub use poly::Poly;
/// The complex type of every spectrum and impedance (re-exported so that callers need no
/// `num-complex` of their own).
pub use realfft::num_complex::Complex64;
pub use simulate::{simulate, SimError, SimOptions, Simulator, Trace};
