//! Indoor texton localisation (indoor seed `indoor-texton-thesis.txt`, ch. 3). So far: the
//! landing trigger ([`landing`], sec. 4.7). The particle filter it is fed from lives in
//! [`crate::filter::particle`]; the texton dictionary, histograms and k-NN come next.

pub mod landing;
