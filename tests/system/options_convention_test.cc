// Every options struct follows one convention: Status Validate() const and
// void Describe(OptionsWriter*) const (libccmd/util/options_writer.h).

#include <set>
#include <string>
#include <type_traits>

#include <gtest/gtest.h>

#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/eval/map_picture.h"
#include "libccmd/eval/plot.h"
#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/features/training_data.h"
#include "libccmd/features/vocabulary_builder.h"
#include "libccmd/io/ply.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/io/tum_recorder.h"
#include "libccmd/net/agent_link.h"
#include "libccmd/net/journal_stage.h"
#include "libccmd/net/refusal_log.h"
#include "libccmd/netsim/delay_line.h"
#include "libccmd/netsim/netns_link.h"
#include "libccmd/optim/bundle_adjuster.h"
#include "libccmd/optim/pose_graph.h"
#include "libccmd/optim/pose_optimizer.h"
#include "libccmd/sensors/retrying_source.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/synth/renderer.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/system/bandwidth_budget.h"
#include "libccmd/system/replay_report.h"
#include "libccmd/system/server_runtime.h"
#include "libccmd/tracking/depth_alignment.h"
#include "libccmd/tracking/options.h"

namespace ccmd {
namespace {

template <typename T, typename = void>
struct FollowsConvention : std::false_type {};
template <typename T>
struct FollowsConvention<
    T, std::enable_if_t<
           std::is_same_v<decltype(std::declval<const T&>().Validate()), Status> &&
           std::is_same_v<
               decltype(std::declval<const T&>().Describe(std::declval<OptionsWriter*>())), void>>>
    : std::true_type {};

template <typename... T>
constexpr bool AllFollow() {
  return (FollowsConvention<T>::value && ...);
}

static_assert(
    AllFollow<ColourEncodeOptions, ColourDecodeOptions, DepthEncodeOptions, DepthDecodeOptions,
              RgbdEncodeOptions, RgbdDecodeOptions, OrbOptions, VocabularyOptions,
              VocabularyBuilderOptions, TrainingImageOptions, RetryOptions, SourceOptions,
              DepthNoise, BaOptions, PoseOptimizationOptions, PoseGraphOptions,
              RgbdSelectionOptions, TrackingOptions, DepthAlignmentOptions, TrafficOptions,
              JournalScanOptions, JournalStageOptions, RefusalLogOptions, ServerOptions,
              AgentLinkOptions, DelayLineOptions, NetnsLinkOptions, LoopVerificationOptions,
              MapPoseGraphOptions, PlaceIndexOptions, SeamOptions, LoopCloserOptions,
              BackendOptions, BackProjectionOptions, DenseMapOptions, SnapshotOptions,
              ReconstructionOptions, AteOptions, RpeOptions, PlotOptions, MapPictureOptions,
              TumOptions, TumRecorderOptions, PlyReadOptions, LoopPathOptions, RoomSceneOptions,
              SyntheticSequenceOptions, RenderOptions, ViewCloudOptions, ViewModelOptions,
              ViewServerOptions, BandwidthBudgetOptions, ReferenceOptions, ServerRuntimeOptions>(),
    "every options struct has Status Validate() const and void Describe(OptionsWriter*) const");

// The value of `name` in the description, or "" when it is not there.
std::string Value(const OptionsWriter& out, const std::string& name) {
  for (const auto& [n, v] : out.entries()) {
    if (n == name) return v;
  }
  return "";
}

TEST(OptionsConventionTest, NestedValuesAreDescribedUnderTheirPathAndNamesAreUnique) {
  ServerRuntimeOptions options;
  options.backend.loops.verification.min_inliers = 77;
  options.backend.dense_options.projection.max_depth_m = 4.25;
  options.net.psk = "a secret that must never be printed";
  OptionsWriter out;
  options.Describe(&out);
  EXPECT_EQ(Value(out, "backend.loops.verification.min_inliers"), "77");
  EXPECT_EQ(Value(out, "backend.dense_options.projection.max_depth_m"), "4.25");
  EXPECT_EQ(Value(out, "net.psk"), "\"set\"");
  std::set<std::string> names;
  for (const auto& [n, v] : out.entries()) {
    EXPECT_TRUE(names.insert(n).second) << "described twice: " << n;
    EXPECT_EQ(v.find("secret"), std::string::npos) << n;
  }
}

TEST(OptionsConventionTest, TrackingOptionsDescribeEveryNestedStruct) {
  TrackingOptions options;
  options.orb.features = 1234;
  options.rgbd_selection.min_threshold = 17;
  options.depth_noise.sigma_2 = 0.004;
  OptionsWriter out;
  options.Describe(&out);
  EXPECT_EQ(Value(out, "orb.features"), "1234");
  EXPECT_EQ(Value(out, "rgbd_selection.min_threshold"), "17");
  EXPECT_EQ(Value(out, "depth_noise.sigma_2"), "0.004");
}

TEST(OptionsConventionTest, ValidateNamesTheBadValue) {
  TrackingOptions tracking;
  tracking.orb.levels = 0;
  EXPECT_NE(tracking.Validate().message().find("levels"), std::string::npos);
  RgbdEncodeOptions rgbd;
  rgbd.jpeg_quality = 0;
  EXPECT_EQ(rgbd.Validate().code(), StatusCode::kInvalidArgument);
  BackendOptions backend;
  backend.loops.verification.ratio = 1.5;
  EXPECT_FALSE(backend.Validate().ok());
  EXPECT_TRUE(BackendOptions().Validate().ok());
}

}  // namespace
}  // namespace ccmd
