#include "libccmd/util/options_writer.h"

#include <cstdlib>
#include <limits>

#include <gtest/gtest.h>

namespace ccmd {
namespace {

struct InnerOptions {
  int count = 3;
  void Describe(OptionsWriter* out) const { out->Add("count", count); }
};

struct OuterOptions {
  double ratio = 0.1;
  bool enabled = true;
  std::string path = "a \"b\"";
  InnerOptions inner;
  void Describe(OptionsWriter* out) const {
    out->Add("ratio", ratio);
    out->Add("enabled", enabled);
    out->Add("path", path);
    out->Nested("inner", inner);
    out->Add("after", 1);
  }
};

TEST(OptionsWriterTest, NestedFieldsAreNamedByTheirPathAndThePrefixEndsWithThem) {
  const std::string text = DescribeOptions(OuterOptions());
  EXPECT_EQ(text,
            "ratio = 0.1\n"
            "enabled = true\n"
            "path = \"a \\\"b\\\"\"\n"
            "inner.count = 3\n"
            "after = 1\n");
}

TEST(OptionsWriterTest, NumbersReadBackExactly) {
  for (const double v : {0.1, 1.0 / 3.0, 5e-4, 1e300, -2.5, 0.0}) {
    OptionsWriter out;
    out.Add("v", v);
    EXPECT_EQ(std::strtod(out.entries()[0].second.c_str(), nullptr), v) << out.entries()[0].second;
  }
  OptionsWriter out;
  out.Add("n", std::numeric_limits<double>::quiet_NaN());
  out.Add("big", std::uint64_t{1} << 40);
  out.Add("list", std::vector<int>{1, 2});
  EXPECT_EQ(out.entries()[0].second, "nan");
  EXPECT_EQ(out.entries()[1].second, "1099511627776");
  EXPECT_EQ(out.entries()[2].second, "[1, 2]");
}

}  // namespace
}  // namespace ccmd
