#include "libccmd/util/status.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

StatusOr<int> Half(int x) {
  if (x % 2) return InvalidArgument("odd");
  return x / 2;
}

StatusOr<int> Quarter(int x) {
  CCMD_ASSIGN_OR_RETURN(const int h, Half(x));
  CCMD_ASSIGN_OR_RETURN(const int q, Half(h));
  return q;
}

TEST(StatusTest, OkAndErrorCarryCodeAndMessage) {
  EXPECT_TRUE(Status::Ok().ok());
  const Status s = Corrupt("bad CRC");
  EXPECT_FALSE(s.ok());
  EXPECT_EQ(s.code(), StatusCode::kCorrupt);
  EXPECT_EQ(s.ToString(), "corrupt: bad CRC");
  EXPECT_EQ(s.WithContext("frame 3").message(), "frame 3: bad CRC");
}

TEST(StatusTest, AssignOrReturnPropagatesTheFirstError) {
  EXPECT_EQ(*Quarter(12), 3);
  EXPECT_EQ(Quarter(6).status().code(), StatusCode::kInvalidArgument);  // 6 -> 3 is odd
  EXPECT_FALSE(Quarter(7).ok());
}

TEST(StatusTest, StatusOrFromOkStatusIsAnError) {
  const StatusOr<int> v = Status::Ok();
  EXPECT_FALSE(v.ok());
  EXPECT_EQ(v.status().code(), StatusCode::kInternal);
}

}  // namespace
}  // namespace ccmd
