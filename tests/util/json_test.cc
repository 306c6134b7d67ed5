#include "libccmd/util/json.h"

#include <gtest/gtest.h>

#include <cmath>

namespace ccmd {
namespace {

TEST(JsonTest, RoundTripKeepsValuesAndEscapes) {
  Json j;
  j["name"] = "a \"quoted\"\nline";
  j["count"] = 42;
  j["ratio"] = 0.125;
  j["flag"] = true;
  j["list"].Push(1);
  j["list"].Push("two");
  j["nested"]["x"] = -3.5e-7;
  for (int indent : {-1, 2}) {
    auto parsed = Json::Parse(j.Dump(indent));
    ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
    EXPECT_EQ(parsed->Get("name")->string(), "a \"quoted\"\nline");
    EXPECT_EQ(parsed->Get("count")->number(), 42);
    EXPECT_EQ(parsed->Get("ratio")->number(), 0.125);
    EXPECT_TRUE(parsed->Get("flag")->boolean());
    ASSERT_EQ(parsed->Get("list")->size(), 2u);
    EXPECT_EQ(parsed->Get("list")->at(1).string(), "two");
    EXPECT_DOUBLE_EQ(parsed->Get("nested")->Get("x")->number(), -3.5e-7);
  }
}

TEST(JsonTest, MalformedInputIsAnErrorNotACrash) {
  for (const char* bad :
       {"", "{", "[1,", "{\"a\" 1}", "tru", "\"unterminated", "[1] x", "{\"a\":}",
        "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[1]"}) {
    EXPECT_FALSE(Json::Parse(bad).ok()) << bad;
  }
}

TEST(JsonTest, NonFiniteNumbersBecomeNull) {
  Json j;
  j["nan"] = std::nan("");
  auto parsed = Json::Parse(j.Dump());
  ASSERT_TRUE(parsed.ok());
  EXPECT_TRUE(parsed->Get("nan")->is_null());
}

}  // namespace
}  // namespace ccmd
