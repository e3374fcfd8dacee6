use super::*;
#[test]
fn scratch_deltas() {
    for path in ["/tmp/lanes2_taylor5exp.safetensors", "python/poisson_rs/models/default.safetensors"] {
        let m = Model::from_file(std::path::Path::new(path)).unwrap();
        let st = m.stepper::<3>(NewtonOptions::default()).unwrap();
        let mut ws = st.workspace();
        let mut rng = Rng::new(1);
        for _ in 0..4 {
            let r = rng.range(1.0, 3.0);
            let mut mu = rng.sphere(r);
            eprintln!("{path} mu {mu:?}");
            st.step(0.1, &mut mu, &mut ws).unwrap();
        }
    }
}
