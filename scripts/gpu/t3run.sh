# Sourced by the GPU scripts that work on a Table 3 run (table3_shared.sh, shared_regressor.sh, reader_levers.sh),
# with run=RUN set: motion and setting from RUN's name after "t3" (/tmp/t3wind: wind, wind-uniform1), and
#   link_trained MODEL SEED RECIPE [VARIANT]   the run's trained model (of VARIANT, default paper) as the
#                                    ablation recipe's, by hard links (nothing retrained); done once, and a link cut
#                                    short never looks finished (linked beside, then renamed). Status 1 when the
#                                    model is not trained.
motion=$(basename "$run" | sed 's/^t3//')
setting=$motion-uniform1
link_trained() {
  local look=${4:-paper}
  local from=$run/train/$setting/$look/$1/s$2 to=$run/ablation/$3/$setting/$look/$1/s$2
  [ -f "$from/DONE" ] || { echo "$from is not trained" >&2; return 1; }
  [ -f "$to/DONE" ] && return 0
  rm -rf "$to" "$to.partial" && mkdir -p "$(dirname "$to")" && cp -al "$from" "$to.partial" && mv "$to.partial" "$to"
}
