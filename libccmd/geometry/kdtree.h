#pragma once

// Nearest-neighbour queries over a fixed set of 3D points (nanoflann KD-tree). The points
// are referenced, not copied: they must outlive the tree and not change.

#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>
#include <nanoflann.hpp>

namespace ccmd {

class PointKdTree {
 public:
  explicit PointKdTree(const std::vector<Eigen::Vector3f>& points)
      : adaptor_{&points},
        index_(
            std::make_unique<Index>(3, adaptor_, nanoflann::KDTreeSingleIndexAdaptorParams(16))) {}

  bool empty() const { return adaptor_.points->empty(); }

  // Index of the nearest point and its squared distance. Precondition: !empty().
  std::uint32_t Nearest(const Eigen::Vector3f& query, float* squared_distance) const {
    std::uint32_t index = 0;
    index_->knnSearch(query.data(), 1, &index, squared_distance);
    return index;
  }

  // The k nearest (fewer if the set is smaller), closest first.
  std::size_t Nearest(const Eigen::Vector3f& query, std::size_t k, std::uint32_t* indices,
                      float* squared_distances) const {
    return index_->knnSearch(query.data(), k, indices, squared_distances);
  }

 private:
  struct Adaptor {
    const std::vector<Eigen::Vector3f>* points;
    std::size_t kdtree_get_point_count() const { return points->size(); }
    float kdtree_get_pt(std::size_t i, std::size_t dim) const { return (*points)[i][dim]; }
    template <class Box>
    bool kdtree_get_bbox(Box&) const {
      return false;
    }
  };
  using Index = nanoflann::KDTreeSingleIndexAdaptor<nanoflann::L2_Simple_Adaptor<float, Adaptor>,
                                                    Adaptor, 3, std::uint32_t>;
  Adaptor adaptor_;
  std::unique_ptr<Index> index_;
};

}  // namespace ccmd
