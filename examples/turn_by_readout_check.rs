//! Research aid: copies a run with its latent turned by the rotation the readout check finds
//! (docs/research/reacher.md, "H"). `cargo run --release --example turn_by_readout_check -- RUN OUT`

use nalgebra::DMatrix;
use procl::model::{LatentEncoder, cpu_device};
use procl::train::orientation::polar_orthogonal;
use procl::train::{RunPaths, TrainedModel};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let [_, from, to] = args.as_slice() else {
        anyhow::bail!("usage: turn_by_readout_check RUN OUT");
    };
    let device = cpu_device();
    let (from, to) = (RunPaths::new(from), RunPaths::new(to));
    let (config, model) = from.load_trained(&device)?;
    let env = from.simulator(&config)?;
    let encoder: &dyn LatentEncoder = match &model {
        TrainedModel::Procl(model) => &model.encoder,
        TrainedModel::Nvae(model) => &model.encoder,
    };
    let Some(check) = procl::eval::readout_check(&env, encoder, &device)? else {
        anyhow::bail!("the response is singular");
    };
    let du = encoder.latent_dim();
    let b = DMatrix::from_row_slice(du, du, &check.response);
    let Some(u) = polar_orthogonal(&b) else {
        anyhow::bail!("the response is singular");
    };
    let p: Vec<f32> = u.iter().map(|&x| x as f32).collect(); // U^T, row-major
    println!("turning by the check's {:?} deg", check.turn_deg);
    std::fs::create_dir_all(&to.dir)?;
    std::fs::copy(from.config(), to.config())?;
    if from.data_record().exists() {
        std::fs::copy(from.data_record(), to.data_record())?;
    }
    let meta = procl::read_checkpoint_meta(&from.checkpoint())?;
    match model {
        TrainedModel::Procl(model) => {
            procl::save_checkpoint(&to.checkpoint(), &model.reorient_latent(&p), None, &meta)?
        }
        TrainedModel::Nvae(model) => {
            let encoder = model.encoder.reorient_readout(&p);
            let model = procl::baselines::nvae::NvaeModel { encoder, ..model };
            procl::save_checkpoint(&to.checkpoint(), &model, None, &meta)?
        }
    }
    Ok(())
}
