//! Indoor texton localisation (indoor seed `indoor-texton-thesis.txt`, ch. 3). So far: the
//! texton dictionary and histograms ([`textons`], sec. 3.3.1-3.3.2) and the landing trigger
//! ([`landing`], sec. 4.7). The particle filter lives in [`crate::filter::particle`]; k-NN,
//! the model file, training and the CLI come next.

pub mod landing;
pub mod textons;
