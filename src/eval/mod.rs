//! Evaluation: the goal-reaching protocol (paper section IV-A), trajectory tracking, their metrics,
//! plots and animations.

mod latent_map;
mod plots;
mod reach;
mod readout;
mod run;
mod track;

pub use latent_map::{
    LatentDiagnostics, config_grid, encode_configs, latent_diagnostics, linear_fit,
    local_map_shares, pushes_away_share,
};
pub use plots::{
    register_font, save_episode_gif, save_latent_plot, save_learning_plot, save_reach_plot,
    save_track_plot,
};
pub use reach::{
    EpisodeRecord, MethodSummary, ReachConfig, ReachReport, TrackSummary, evaluate_reach,
    reach_tasks, run_episode, summarise,
};
pub use readout::{READOUT_CHECK_HORIZON, ReadoutCheck, readout_check};
pub use run::{
    Controller, EvalOutputs, LATENT_MAP, RunPolicy, evaluate_oracle, evaluate_run,
    evaluate_run_with, run_policy, write_diagnostics, write_env_diagnostics,
};
pub use track::{Reference, TRACK_FIGURE, TrackReport, track_episode, track_run};
