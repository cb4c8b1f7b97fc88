"""Every metric moex reports, in one table: its column name in metrics.csv / history.csv, the
paper's symbol as a matplotlib mathtext label, the words the log uses and how figures scale it.
The evaluation, the log, the report and the figures read their names and labels from here;
adding a metric touches its function and one row."""

from dataclasses import dataclass


@dataclass(frozen=True)
class Metric:
    name: str  # column name
    label: str  # for figures (mathtext), e.g. r"$E^g$"
    text: str  # for the log and Markdown, e.g. "E^g"
    meaning: str
    scale: str = "linear"  # linear | log | symlog (an exponent: its sign matters)
    logged: bool = False  # in the per-run summary line of the log
    reported: bool = False  # a column of `moex report`'s tables
    # computed on the closed loop with the noise of eval.noise_var added to x_n; every other
    # metric (max_lyapunov and its companions included, as in the paper) on the noiseless loop
    noisy: bool = False


METRICS = {m.name: m for m in [
    Metric("E", r"mixture error $E$", "E", "½‖y − Σ g^k y^k‖² per step and feature, teacher "
           "forced (Sec. 3)", "log", logged=True, reported=True),
    Metric("E_g", r"gating error $E^g$", "E^g", "KL from ĝ to the gating RNN's g per step and "
           "gate (Eq. 16)", "log", logged=True, reported=True),
    Metric("E_closed", r"closed-loop error $E^{\mathrm{closed}}$", "E^closed",
           "E of the closed loop from the trained initial states", "log", logged=True,
           reported=True),
    Metric("block_kl_train", r"block KL $D^{(m)}_{\mathrm{KL}}$, training data",
           "block KL train", "KL of symbol blocks, data against the closed loop (Eq. 21)",
           logged=True, reported=True),
    Metric("block_kl_test", r"block KL $D^{(m)}_{\mathrm{KL}}$, test data", "block KL test",
           "the same against held-out series", logged=True, reported=True, noisy=True),
    Metric("max_lyapunov", r"$\lambda_{\max}$", "λ_max", "largest Lyapunov exponent of the "
           "closed loop, per step (Sec. 4)", "symlog", logged=True, reported=True),
    Metric("max_lyapunov_noisy", r"$\lambda_{\max}$ with noise", "λ_max with noise",
           "the same with input noise of eval.noise_var", "symlog", noisy=True),
    Metric("lyapunov_positive", r"share with $\lambda_{\max} > 0$", "λ_max > 0",
           "the paper's criterion of chaos, λ_max > 0, without its error (the column `chaos` "
           "has the label with it)"),
    Metric("max_lyapunov_se", r"standard error of $\lambda_{\max}$", "λ_max s.e.",
           "sd of the samples' own exponents / √samples: |λ_max| below about twice it is not "
           "told apart from 0", "log"),
    Metric("positive_sample_fraction", r"share of samples with $\lambda > 0$",
           "samples with λ > 0", "share of initial states whose own exponent is positive"),
    Metric("switch_rate", "switches per step", "switch rate",
           "changes of primitive per closed-loop step", noisy=True),
    Metric("censored_stays", "stays cut off by a sample's end", "cut-off stays",
           "stays at the end of a sample, counted at their observed length", noisy=True),
    Metric("periodicity_samples", "samples judged for periodicity", "judged samples",
           "samples long enough to test every period up to eval.max_period", noisy=True),
    Metric("switch_prob", "switching probability", "switching prob.", "probability of "
           "changing primitive at a primitive's end", logged=True, reported=True, noisy=True),
    Metric("switch_prob_gates", "switching probability (gates)", "switching prob. (gates)",
           "the same read off the winning gate", reported=True, noisy=True),
    Metric("data_switch_prob", "switching probability of the data", "data switching prob.",
           "the same in the training data", logged=True, reported=True),
    Metric("mean_residence", "mean residence (repetitions)", "mean residence",
           "repetitions of a primitive before a switch", reported=True, noisy=True),
    Metric("nonperiodic_fraction", "share of nonperiodic samples", "nonperiodic",
           "samples whose symbol sequence has no period up to eval.max_period", logged=True,
           reported=True, noisy=True),
    Metric("segment_ari", "adjusted Rand index", "ARI", "the winning expert per step of the "
           "training series (ĝ) against their labels: 1 the same segments, 0 chance",
           logged=True, reported=True),
    Metric("segment_nmi", "normalised mutual information", "NMI",
           "the same as mutual information over the mean entropy", reported=True),
    Metric("segment_accuracy", "accuracy after matching", "accuracy",
           "share of steps whose expert is matched to their label (best one-to-one matching)",
           logged=True, reported=True),
    Metric("segment_ari_test", "adjusted Rand index, test data", "ARI test",
           "the held-out series', segmented by moex segment's smooth method", reported=True),
    Metric("segment_nmi_test", "normalised mutual information, test data", "NMI test",
           "the same, normalised mutual information"),
    Metric("segment_accuracy_test", "accuracy after matching, test data", "accuracy test",
           "the same, accuracy after matching", reported=True),
    Metric("label_block_kl", "block KL of the labels", "label block KL",
           "the data's labels against the closed loop's winning experts read as labels through "
           "the training data's matching (Eq. 21 on per-step labels)", reported=True),
    Metric("label_mean_stay", "mean stay on a label (steps)", "label stay",
           "the closed loop's, its experts read as labels", reported=True),
    Metric("data_label_mean_stay", "mean stay on a label in the data (steps)", "data label stay",
           "the same in the training data", reported=True),
    Metric("log_likelihood", r"$\ln p(Y \mid X, \theta)$", "ln L",
           "phase-1 log-likelihood (Eqs. 10-12)"),
    Metric("kl", r"$D_{\mathrm{KL}}(\hat g \,\|\, g)$", "KL", "phase-2 KL summed over the data"),
    Metric("lr_scale", r"adaptive rate $\alpha / \tilde\alpha$", "α/α̃",
           "the adaptive learning rate's factor (Sec. 2.1.4)", "log"),
]}


def label(name: str) -> str:
    """The figure label of a column (the column name itself if it is not a metric)."""
    return METRICS[name].label if name in METRICS else name


# metrics.csv columns that are settings, bookkeeping or labels, not measurements: `chaos` is
# chaotic / not chaotic / undetermined (moex.metrics.lyapunov.chaos_label), lyapunov_samples the
# initial states λ_max was averaged over; lyapunov_k (k >= 2, with eval.num_exponents > 1) are the
# further exponents
NOT_METRICS = ("run", "failed", "block_length", "noise_var", "num_samples", "lyapunov_steps",
               "noise_enters", "chaos", "lyapunov_samples")


def is_known(column: str) -> bool:
    """Whether a metrics.csv column is in the table (or a setting it records)."""
    return column in METRICS or column in NOT_METRICS or (
        column.startswith("lyapunov_") and column.removeprefix("lyapunov_").isdigit())


LOGGED = [m.name for m in METRICS.values() if m.logged]
REPORTED = [m.name for m in METRICS.values() if m.reported]
NOISY = [m.name for m in METRICS.values() if m.noisy]
