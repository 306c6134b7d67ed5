#include "libccmd/backend/loop_options.h"

#include <cmath>

namespace ccmd {

Status SeamOptions::Validate() const {
  if (keyframes < 1) return InvalidArgument("seam keyframes must be >= 1");
  for (const double v : {search_radius_px, merge_radius_px, search_depth_m, merge_depth_m,
                         max_correction_m, max_correction_deg}) {
    if (!(v > 0) || !std::isfinite(v))
      return InvalidArgument("seam radii, depth tolerances and corrections must be positive");
  }
  if (max_hamming < 1 || max_hamming > 256)
    return InvalidArgument("seam max Hamming distance must be 1..256");
  if (min_pairs < 3) return InvalidArgument("seam refinement needs at least 3 pairs");
  return Status::Ok();
}

void SeamOptions::Describe(OptionsWriter* out) const {
  out->Add("enabled", enabled);
  out->Add("keyframes", keyframes);
  out->Add("search_radius_px", search_radius_px);
  out->Add("merge_radius_px", merge_radius_px);
  out->Add("search_depth_m", search_depth_m);
  out->Add("merge_depth_m", merge_depth_m);
  out->Add("max_hamming", max_hamming);
  out->Add("min_pairs", min_pairs);
  out->Add("max_correction_m", max_correction_m);
  out->Add("max_correction_deg", max_correction_deg);
}

Status FusionOverlapOptions::Validate() const {
  if (max_pairs < 0 || tied_points < 0)
    return InvalidArgument("fusion overlap pairs and tied points must be >= 0");
  for (const double v : {max_distance_m, max_angle_deg, spacing_m}) {
    if (!(v > 0) || !std::isfinite(v))
      return InvalidArgument("fusion overlap distance, angle and spacing must be positive");
  }
  return Status::Ok();
}

void FusionOverlapOptions::Describe(OptionsWriter* out) const {
  out->Add("max_pairs", max_pairs);
  out->Add("max_distance_m", max_distance_m);
  out->Add("max_angle_deg", max_angle_deg);
  out->Add("spacing_m", spacing_m);
  out->Add("tied_points", tied_points);
}

Status LoopCloserOptions::Validate() const {
  if (loop_candidates < 1) return InvalidArgument("loop candidates must be >= 1");
  if (loop_consistency < 1) return InvalidArgument("loop consistency must be >= 1");
  if (verification.min_inliers < 10) return InvalidArgument("loop min inliers must be >= 10");
  if (consistency_max_gap < 1) return InvalidArgument("loop consistency gap must be >= 1");
  if (neighbour_checks < 0) return InvalidArgument("loop neighbour checks must be >= 0");
  if (!(consistency_translation > 0) || !(consistency_rotation_deg > 0)) {
    return InvalidArgument("loop consistency tolerances must be positive");
  }
  if (exclude_recent_keyframes < 0 || loop_cooldown_keyframes < 0) {
    return InvalidArgument("loop exclusion and cool-down must be >= 0 keyframes");
  }
  if (!(min_correction_m >= 0) || !(min_correction_deg >= 0)) {
    return InvalidArgument("the smallest loop correction must be >= 0");
  }
  CCMD_RETURN_IF_ERROR(verification.Validate());
  CCMD_RETURN_IF_ERROR(seam.Validate());
  CCMD_RETURN_IF_ERROR(overlap.Validate());
  return pose_graph.Validate();
}

void LoopCloserOptions::Describe(OptionsWriter* out) const {
  out->Nested("verification", verification);
  out->Nested("seam", seam);
  out->Nested("overlap", overlap);
  out->Add("loop_candidates", loop_candidates);
  out->Add("loop_consistency", loop_consistency);
  out->Add("consistency_translation", consistency_translation);
  out->Add("consistency_rotation_deg", consistency_rotation_deg);
  out->Add("consistency_max_gap", consistency_max_gap);
  out->Add("neighbour_checks", neighbour_checks);
  out->Add("exclude_recent_keyframes", exclude_recent_keyframes);
  out->Add("loop_cooldown_keyframes", loop_cooldown_keyframes);
  out->Add("min_correction_m", min_correction_m);
  out->Add("min_correction_deg", min_correction_deg);
  out->Nested("pose_graph", pose_graph);
}

}  // namespace ccmd
