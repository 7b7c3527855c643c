// Host side of the ops that edit the integer tables a cut changes (their schemas: schema.cpp;
// registered for the CPU with the rest of the family: ops.h, cpu.cpp): what
// TensorMass.repoint_elements plans on the host (ElementGroup.cut_tables: the group's elements,
// its gather plan's force_index, incidences and lists node_items, for the hooke tensor form its
// edges, edge_slots and element_edges; the model's node_slots), as one call per cut.
//
// A cut re-points a few elements to new nodes: the tables change only in the lists of the nodes
// and edges those elements leave and join. Each op works in three steps, so that a check that
// fails (a precondition broken, or for the hooke tensor form a plan or an edge pool too small)
// leaves every table as it was:
//   1. plan and check, the tables only read: the entries that change, the hooke tensor form's
//      new and emptied edges and the room they need; the lists to edit are copied into a
//      workspace (ListColumns) and edited there;
//   2. write: the workspace's lists, then counts, slots, edges and elements, into the tables;
//   3. the results, read from the tables where the reference reads them after its edits.
// Each step follows its reference (tensormass_torch.ops.cutting, which holds the Python that
// TensorMass and ElementGroup ran) one for one, orders included: a list keeps its order when an
// item leaves it, items join in the order given, every id set comes out sorted and unique. The
// tables and results are then the reference's, bit for bit. The cost is O(changed entries x
// slots), but for the hooke tensor form's room check, which looks at every node's count as the
// reference does (an untouched node may already fill the plan).
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cstdint>
#include <limits>
#include <numeric>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "common/checks.h"
#include "common/dispatch.h"

namespace tensormass {
namespace cutting {

// An id -> value map for the few ids a cut touches (open addressing, linear probing; ids >= 0).
class IdMap {
 public:
  explicit IdMap(size_t expected = 0) {
    size_t capacity = 16;
    while (capacity < 2 * expected) capacity *= 2;
    keys_.assign(capacity, -1);
    values_.resize(capacity);
  }

  // The value of id, and whether it was absent (it then holds `value`).
  std::pair<int64_t*, bool> emplace(int64_t id, int64_t value) {
    if (2 * (size_ + 1) > keys_.size()) grow();
    size_t i = slot_of(id);
    while (keys_[i] >= 0 && keys_[i] != id) i = (i + 1) & (keys_.size() - 1);
    if (keys_[i] == id) return {&values_[i], false};
    keys_[i] = id, values_[i] = value, ++size_;
    return {&values_[i], true};
  }

  const int64_t* find(int64_t id) const {
    for (size_t i = slot_of(id);; i = (i + 1) & (keys_.size() - 1)) {
      if (keys_[i] == id) return &values_[i];
      if (keys_[i] < 0) return nullptr;
    }
  }

  // f(id, value) for every id (in no particular order).
  template <class F>
  void for_each(F&& f) const {
    for (size_t i = 0; i < keys_.size(); ++i) {
      if (keys_[i] >= 0) f(keys_[i], values_[i]);
    }
  }

 private:
  size_t slot_of(int64_t id) const {
    return static_cast<size_t>((static_cast<uint64_t>(id) * 0x9E3779B97F4A7C15ull) >> 17) & (keys_.size() - 1);
  }

  void grow() {
    std::vector<int64_t> keys(std::move(keys_)), values(std::move(values_));
    keys_.assign(2 * keys.size(), -1);
    values_.resize(keys_.size());
    size_ = 0;
    for (size_t i = 0; i < keys.size(); ++i) {
      if (keys[i] >= 0) emplace(keys[i], values[i]);
    }
  }

  std::vector<int64_t> keys_, values_;
  size_t size_ = 0;
};

// Sorts items by key(item), every key in [0, range): stable (a radix sort, as few passes of at
// most 11 bits as the range takes; std::stable_sort for a few items).
template <class T, class Key>
void sort_by_key(std::vector<T>& items, int64_t range, Key key) {
  for (const T& item : items) {
    TORCH_CHECK(key(item) >= 0 && key(item) < range, "tensormass: internal error: a sort key outside its range");
  }
  if (items.size() < 64) {
    std::stable_sort(items.begin(), items.end(), [&](const T& a, const T& b) { return key(a) < key(b); });
    return;
  }
  int bits = 0;
  while (bits < 63 && ((range - 1) >> bits) > 0) ++bits;
  const int passes = (bits + 10) / 11, digit = passes ? (bits + passes - 1) / passes : 0;
  const int64_t mask = (int64_t(1) << digit) - 1;
  std::vector<T> sorted(items.size());
  std::vector<size_t> start((size_t(1) << digit) + 1);
  for (int shift = 0; shift < bits; shift += digit) {
    std::fill(start.begin(), start.end(), 0);
    for (const T& item : items) ++start[((key(item) >> shift) & mask) + 1];
    if (start[((key(items[0]) >> shift) & mask) + 1] == items.size()) continue;  // one digit: nothing moves
    for (size_t b = 0; b + 1 < start.size(); ++b) start[b + 1] += start[b];
    for (const T& item : items) sorted[start[(key(item) >> shift) & mask]++] = item;
    items.swap(sorted);
  }
}

// v sorted and unique (every value in [0, range)).
inline void sort_unique(std::vector<int64_t>& v, int64_t range) {
  sort_by_key(v, range, [](int64_t x) { return x; });
  v.erase(std::unique(v.begin(), v.end()), v.end());
}

// Asks for the cache line of p ahead of its use: the lists' entries are far apart, each read a
// cache miss that the loops below overlap by asking kAhead entries ahead.
constexpr int64_t kAhead = 16;
inline void prefetch(const void* p) {
#if defined(__GNUC__)
  __builtin_prefetch(p);
#else
  (void)p;
#endif
}

// The lists of a few targets of a padded incidence table [S, T] (slot s of target t at s T + t;
// -1 past the last), copied out whole, edited here and written back (write). They are copied and
// written a row of the table at a time, the targets in ascending order: the table is large and
// its lists strided, so that each row is read in address order (a list at a time would touch S
// pages per list).
template <typename I>
class ListColumns {
 public:
  ListColumns(I* table, int64_t num_slots, int64_t num_targets)
      : table_(table), num_slots_(num_slots), num_targets_(num_targets) {}

  int64_t num_slots() const { return num_slots_; }
  int64_t num_targets() const { return num_targets_; }

  // Copies the lists of `targets` (sorted, unique, in [0, T)) not copied yet.
  void load(const std::vector<int64_t>& targets) {
    std::vector<int64_t> fresh;
    for (const int64_t t : targets) {
      if (position_.emplace(t, static_cast<int64_t>(targets_.size() + fresh.size())).second) fresh.push_back(t);
    }
    const int64_t first = static_cast<int64_t>(targets_.size()), count = static_cast<int64_t>(fresh.size());
    targets_.insert(targets_.end(), fresh.begin(), fresh.end());
    data_.resize(targets_.size() * num_slots_);
    for (int64_t s = 0; s < num_slots_; ++s) {
      const I* row = table_ + s * num_targets_;
      I* out = data_.data() + first * num_slots_ + s;
      for (int64_t c = 0; c < count; ++c) {
        if (c + kAhead < count) prefetch(row + fresh[c + kAhead]);
        out[c * num_slots_] = row[fresh[c]];
      }
    }
    // each list's extent as copied: past it the table holds -1
    extent_.resize(targets_.size());
    for (int64_t c = first; c < first + count; ++c) extent_[c] = extent(c);
  }

  // The list of target t (copied before).
  I* list(int64_t t) {
    const int64_t* p = position_.find(t);
    TORCH_CHECK(p != nullptr, "tensormass: internal error: a list edited before it was copied");
    return data_.data() + *p * num_slots_;
  }

  // Every list copied, written back into the table: the slots up to the larger of its extents as
  // copied and now (past both, the table and the list hold -1).
  void write() const {
    std::vector<int64_t> order(targets_.size()), written(targets_.size());
    std::iota(order.begin(), order.end(), 0);
    sort_by_key(order, num_targets_, [&](int64_t p) { return targets_[p]; });
    int64_t rows = 0;
    for (size_t p = 0; p < targets_.size(); ++p) {
      written[p] = std::max(extent_[p], extent(static_cast<int64_t>(p)));
      rows = std::max(rows, written[p]);
    }
    for (int64_t s = 0; s < rows; ++s) {
      I* row = table_ + s * num_targets_;
      for (size_t k = 0; k < order.size(); ++k) {
        if (k + kAhead < order.size()) prefetch(row + targets_[order[k + kAhead]]);
        const int64_t p = order[k];
        if (s < written[p]) row[targets_[p]] = data_[p * num_slots_ + s];
      }
    }
  }

  // The lists of `targets` (copied before) as they are now, [S, C] of `type`.
  at::Tensor columns(const std::vector<int64_t>& targets, at::ScalarType type) {
    const int64_t count = static_cast<int64_t>(targets.size());
    at::Tensor out = at::empty({num_slots_, count}, at::TensorOptions().dtype(type));
    I* o = out.data_ptr<I>();
    for (int64_t c = 0; c < count; ++c) {
      const I* l = list(targets[c]);
      for (int64_t s = 0; s < num_slots_; ++s) o[s * count + c] = l[s];
    }
    return out;
  }

 private:
  // One past the last slot of the list at position p that is not -1.
  int64_t extent(int64_t p) const {
    const I* list = data_.data() + p * num_slots_;
    int64_t end = num_slots_;
    while (end > 0 && list[end - 1] == -1) --end;
    return end;
  }

  I* table_;
  int64_t num_slots_, num_targets_;
  IdMap position_;
  std::vector<int64_t> targets_;  // in the order copied
  std::vector<I> data_;           // list p at p S
  std::vector<int64_t> extent_;   // as copied
};

// topology.remove_from_lists: items[k] leaves the list of targets[k] (lists copied before). In
// each target's list as it was before any of its items left, the first slot holding the item goes
// (slot 0 where none holds it: the reference's argmax over no match); the ids >= 0 left are packed
// from slot 0 in order, -1 after. The lists touched: the targets, sorted and unique.
template <typename I>
void remove_from_lists(ListColumns<I>& lists, const std::vector<int64_t>& targets, const std::vector<int64_t>& items,
                       const char* table_name) {
  const int64_t num_slots = lists.num_slots();
  if (targets.empty()) return;
  TORCH_CHECK(num_slots > 0, "tensormass: ", table_name, " has no slot to remove an item from");
  std::vector<std::pair<int64_t, int64_t>> leaving(targets.size());
  for (size_t k = 0; k < targets.size(); ++k) leaving[k] = {targets[k], items[k]};
  sort_by_key(leaving, lists.num_targets(), [](const std::pair<int64_t, int64_t>& p) { return p.first; });
  std::vector<char> gone(num_slots);
  for (size_t begin = 0; begin < leaving.size();) {
    const int64_t target = leaving[begin].first;
    size_t end = begin;
    while (end < leaving.size() && leaving[end].first == target) ++end;
    I* list = lists.list(target);
    std::fill(gone.begin(), gone.end(), 0);
    for (size_t k = begin; k < end; ++k) {
      const I item = static_cast<I>(leaving[k].second);
      int64_t slot = 0;
      for (int64_t s = 0; s < num_slots; ++s) {
        if (list[s] == item) {
          slot = s;
          break;
        }
      }
      gone[slot] = 1;
    }
    int64_t kept = 0;
    for (int64_t s = 0; s < num_slots; ++s) {
      if (list[s] >= 0 && !gone[s]) list[kept++] = list[s];
    }
    std::fill(list + kept, list + num_slots, static_cast<I>(-1));
    begin = end;
  }
}

// The model's lists (node_slots: model element ids; those of old_nodes and new_nodes copied before)
// edited as TensorMass.repoint_elements edits them: moved_ids[k] leaves the list of old_nodes[k]
// (remove_from_lists), then joins that of new_nodes[k] after the ids listed there
// (topology.list_counts: the ids >= 0 of the list) and the ids joining before it. The lists
// changed: those of old_nodes and new_nodes.
template <typename I>
void edit_node_lists(ListColumns<I>& lists, const std::vector<int64_t>& old_nodes,
                     const std::vector<int64_t>& new_nodes, const std::vector<int64_t>& moved_ids) {
  remove_from_lists(lists, old_nodes, moved_ids, "node_slots");
  const int64_t num_slots = lists.num_slots();
  IdMap next_slot(new_nodes.size());  // node -> the slot its next id takes
  for (size_t k = 0; k < new_nodes.size(); ++k) {
    const int64_t node = new_nodes[k];
    I* list = lists.list(node);
    auto found = next_slot.emplace(node, 0);
    if (found.second) {
      for (int64_t s = 0; s < num_slots; ++s) *found.first += list[s] >= 0;
    }
    const int64_t slot = (*found.first)++;
    TORCH_CHECK(slot < num_slots, "tensormass: node_slots has ", std::to_string(num_slots), " slots but node ",
                std::to_string(node), " of nodes would list ", std::to_string(slot + 1),
                " elements (a new node takes elements of one node)");
    list[slot] = static_cast<I>(moved_ids[k]);
  }
}

// A group's gather plan being edited: its lists (node_items [S, V]: items row w + a), counts
// (incidences [V]) and slots (force_index, flat), the writes held until every check passed.
template <typename I>
struct PlanLists {
  ListColumns<I> items;
  const I* incidences;
  int64_t num_items;                                     // force_index.numel()
  IdMap counts;                                          // node -> its incidences after the edit
  std::vector<std::pair<int64_t, int64_t>> slot_writes;  // (item, slot), in the reference's order

  PlanLists(I* node_items, int64_t num_slots, int64_t num_nodes, const I* incidences_, int64_t num_items_)
      : items(node_items, num_slots, num_nodes), incidences(incidences_), num_items(num_items_) {}

  int64_t count(int64_t node) const {
    const int64_t* edited = counts.find(node);
    return edited == nullptr ? static_cast<int64_t>(incidences[node]) : *edited;
  }

  void write(I* force_index, I* incidence_table) const {
    items.write();
    for (const auto& w : slot_writes) force_index[w.first] = static_cast<I>(w.second);
    counts.for_each([&](int64_t node, int64_t count) { incidence_table[node] = static_cast<I>(count); });
  }
};

// ElementGroup._edit_lists (the lists of gone_nodes and new_nodes copied before): the items
// gone_items[k] leave the lists of gone_nodes[k] (packed in order; each item left in those lists
// gets its slot as force_index, and each list its count as incidences), then new_items[k] join
// new_nodes[k] at incidences + their rank among the items joining that node. The nodes whose
// incidences changed: gone_nodes and new_nodes; returns the items whose force_index did, sorted
// and unique.
template <typename I>
std::vector<int64_t> edit_plan_lists(PlanLists<I>& plan, const std::vector<int64_t>& gone_items,
                                     const std::vector<int64_t>& gone_nodes, const std::vector<int64_t>& new_items,
                                     const std::vector<int64_t>& new_nodes) {
  std::vector<int64_t> items(new_items);
  const int64_t num_slots = plan.items.num_slots();
  if (!gone_items.empty()) {
    remove_from_lists(plan.items, gone_nodes, gone_items, "node_items");
    std::vector<int64_t> touched(gone_nodes);
    sort_unique(touched, plan.items.num_targets());
    std::vector<I*> lists(touched.size());
    for (size_t c = 0; c < touched.size(); ++c) lists[c] = plan.items.list(touched[c]);
    std::vector<int64_t> kept(touched.size(), 0);
    // slot by slot over the lists, as the reference's mask of the [S, K] lists orders the items
    for (int64_t s = 0; s < num_slots; ++s) {
      for (size_t c = 0; c < touched.size(); ++c) {
        const int64_t item = lists[c][s];
        if (item < 0) continue;
        TORCH_CHECK(item < plan.num_items, "tensormass: node_items lists item ", std::to_string(item),
                    ", outside the ", std::to_string(plan.num_items), " items of force_index");
        plan.slot_writes.emplace_back(item, s);
        items.push_back(item);
        ++kept[c];
      }
    }
    for (size_t c = 0; c < touched.size(); ++c) *plan.counts.emplace(touched[c], 0).first = kept[c];
  }
  IdMap next_slot(new_nodes.size());  // node -> the slot its next item takes
  for (size_t k = 0; k < new_items.size(); ++k) {
    const int64_t node = new_nodes[k];
    auto found = next_slot.emplace(node, 0);
    if (found.second) *found.first = plan.count(node);
    const int64_t slot = (*found.first)++;
    TORCH_CHECK(slot >= 0 && slot < num_slots, "tensormass: node_items has ", std::to_string(num_slots),
                " slots but node ", std::to_string(node), " would take item ", std::to_string(new_items[k]),
                " in slot ", std::to_string(slot));
    TORCH_CHECK(new_items[k] >= 0 && new_items[k] < plan.num_items, "tensormass: item ", std::to_string(new_items[k]),
                " is outside the ", std::to_string(plan.num_items), " items of force_index");
    plan.items.list(node)[slot] = static_cast<I>(new_items[k]);
    plan.slot_writes.emplace_back(new_items[k], slot);
  }
  next_slot.for_each([&](int64_t node, int64_t next) { *plan.counts.emplace(node, 0).first = next; });
  sort_unique(items, plan.num_items);
  return items;
}

// The entries of the re-pointed elements (rows [M], nodes [M, NN]) whose node changes, in row-major
// order, and the rows' nodes before (the elements' rows, copied before anything is written).
struct Changes {
  std::vector<int64_t> entry;     // m NN + a
  std::vector<int64_t> old_node;  // elements[rows[m], a]
  std::vector<int64_t> new_node;  // nodes[m, a]
  std::vector<int64_t> id;        // ids[m]
};

template <typename I, int NN>
Changes changed_entries(const I* elements, int64_t num_elements, int64_t num_nodes, const I* rows, const int64_t* ids,
                        const I* nodes, int64_t num_rows, std::vector<I>& old_rows) {
  Changes c;
  old_rows.resize(num_rows * NN);
  for (int64_t m = 0; m < num_rows; ++m) {
    const int64_t row = rows[m];
    TORCH_CHECK(row >= 0 && row < num_elements, "tensormass: rows holds ", std::to_string(row), ", outside the ",
                std::to_string(num_elements), " elements");
    for (int a = 0; a < NN; ++a) {
      const int64_t before = elements[row * NN + a], after = nodes[m * NN + a];
      TORCH_CHECK(before >= 0 && before < num_nodes, "tensormass: elements: row ", std::to_string(row), " holds node ",
                  std::to_string(before), ", outside the ", std::to_string(num_nodes), " nodes of incidences");
      TORCH_CHECK(after >= 0 && after < num_nodes, "tensormass: nodes holds ", std::to_string(after), ", outside the ",
                  std::to_string(num_nodes), " nodes of incidences");
      old_rows[m * NN + a] = static_cast<I>(before);
      if (before != after) {
        c.entry.push_back(m * NN + a);
        c.old_node.push_back(before);
        c.new_node.push_back(after);
        c.id.push_back(ids[m]);
      }
    }
  }
  return c;
}

// The nodes whose lists change: those the changed entries leave and join, sorted and unique.
inline std::vector<int64_t> changed_nodes(const Changes& c, int64_t num_nodes) {
  std::vector<int64_t> nodes(c.old_node);
  nodes.insert(nodes.end(), c.new_node.begin(), c.new_node.end());
  sort_unique(nodes, num_nodes);
  return nodes;
}

template <typename I>
at::Tensor index_tensor(const std::vector<int64_t>& values, at::ScalarType type) {
  at::Tensor out = at::empty({static_cast<int64_t>(values.size())}, at::TensorOptions().dtype(type));
  if (type == at::kLong) {
    std::copy(values.begin(), values.end(), out.data_ptr<int64_t>());
  } else {
    I* o = out.data_ptr<I>();
    for (size_t i = 0; i < values.size(); ++i) o[i] = static_cast<I>(values[i]);
  }
  return out;
}

// table[ids] of a flat table (of I), as I.
template <typename I>
at::Tensor gathered(const I* table, const std::vector<int64_t>& ids, at::ScalarType type) {
  at::Tensor out = at::empty({static_cast<int64_t>(ids.size())}, at::TensorOptions().dtype(type));
  I* o = out.data_ptr<I>();
  for (size_t i = 0; i < ids.size(); ++i) o[i] = table[ids[i]];
  return out;
}

// cat([old rows, nodes]) [2M, NN].
template <typename I, int NN>
at::Tensor both_rows(const std::vector<I>& old_rows, const I* nodes, int64_t num_rows, at::ScalarType type) {
  at::Tensor out = at::empty({2 * num_rows, NN}, at::TensorOptions().dtype(type));
  I* o = out.data_ptr<I>();
  std::copy(old_rows.begin(), old_rows.end(), o);
  std::copy(nodes, nodes + num_rows * NN, o + num_rows * NN);
  return out;
}

using ElementTablesResult = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

// cutting_edit_element_tables (schema.cpp): a group whose plan's items are its elements.
template <typename I, int NN>
ElementTablesResult edit_element_tables(at::Tensor& elements, at::Tensor& force_index, at::Tensor& incidences,
                                        at::Tensor& node_items, at::Tensor& node_slots, const at::Tensor& rows,
                                        const at::Tensor& ids, const at::Tensor& nodes) {
  const at::ScalarType type = elements.scalar_type();
  const int64_t num_rows = rows.size(0), num_nodes = incidences.size(0);
  I* el = elements.data_ptr<I>();
  const I* nd = nodes.data_ptr<I>();
  const I* row = rows.data_ptr<I>();
  std::vector<I> old_rows;
  const Changes c = changed_entries<I, NN>(el, elements.size(0), num_nodes, row, ids.data_ptr<int64_t>(), nd, num_rows,
                                           old_rows);

  // 1. the edits, in workspaces: each changed entry's element leaves the old node's lists and
  // joins the new node's (the plan's items: row n + a)
  const std::vector<int64_t> nodes_changed = changed_nodes(c, num_nodes);
  ListColumns<I> model_lists(node_slots.data_ptr<I>(), node_slots.size(0), num_nodes);
  model_lists.load(nodes_changed);
  edit_node_lists(model_lists, c.old_node, c.new_node, c.id);
  PlanLists<I> plan(node_items.data_ptr<I>(), node_items.size(0), num_nodes, incidences.data_ptr<I>(),
                    force_index.numel());
  plan.items.load(nodes_changed);
  std::vector<int64_t> items(c.entry.size());
  for (size_t k = 0; k < items.size(); ++k) items[k] = static_cast<int64_t>(row[c.entry[k] / NN]) * NN + c.entry[k] % NN;
  const std::vector<int64_t> items_changed = edit_plan_lists(plan, items, c.old_node, items, c.new_node);

  // 2. the writes
  model_lists.write();
  plan.write(force_index.data_ptr<I>(), incidences.data_ptr<I>());
  for (int64_t m = 0; m < num_rows; ++m) std::copy(nd + m * NN, nd + (m + 1) * NN, el + static_cast<int64_t>(row[m]) * NN);

  // 3. the results
  return {index_tensor<I>(nodes_changed, at::kLong), gathered<I>(incidences.data_ptr<I>(), nodes_changed, type),
          index_tensor<I>(items_changed, at::kLong), gathered<I>(force_index.data_ptr<I>(), items_changed, type),
          index_tensor<I>(nodes_changed, at::kLong), model_lists.columns(nodes_changed, type),
          both_rows<I, NN>(old_rows, nd, num_rows, type)};
}

using EdgeTablesResult =
    std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor,
               at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

inline at::Tensor status_tensor(int64_t need, int64_t count, bool edited) {
  at::Tensor status = at::empty({3}, at::TensorOptions().dtype(at::kLong));
  int64_t* s = status.data_ptr<int64_t>();
  s[0] = need, s[1] = count, s[2] = edited ? 1 : 0;
  return status;
}

// The edge op's results where it edits nothing: the status and empty tensors of the results' ranks.
inline EdgeTablesResult unedited(at::Tensor status, at::ScalarType type, int64_t edge_list_slots, int64_t pairs,
                                 int64_t node_list_slots, int64_t nodes_per_element) {
  const auto index = at::TensorOptions().dtype(type);
  const auto wide = at::TensorOptions().dtype(at::kLong);
  return {status, at::empty({0}, index), at::empty({0}, wide), at::empty({0}, index), at::empty({0}, wide),
          at::empty({0}, index), at::empty({0}, wide), at::empty({0}, index), at::empty({0}, wide),
          at::empty({edge_list_slots, 0}, index), at::empty({0}, wide), at::empty({0, 2}, index),
          at::empty({0, pairs}, index), at::empty({0}, wide), at::empty({node_list_slots, 0}, index),
          at::empty({0, nodes_per_element}, index)};
}

// cutting_edit_edge_tables (schema.cpp): a hooke tensor-form group, whose plan's items are its
// edges (item = edge 2 + end).
template <typename I, int NN>
EdgeTablesResult edit_edge_tables(at::Tensor& elements, at::Tensor& force_index, at::Tensor& incidences,
                                  at::Tensor& node_items, at::Tensor& node_slots, at::Tensor& edges,
                                  at::Tensor& edge_slots, at::Tensor& element_edges, const at::Tensor& rows,
                                  const at::Tensor& ids, const at::Tensor& nodes, const at::Tensor& element_row,
                                  const at::Tensor& removed, int64_t edge_rows_used) {
  constexpr int NP = NN * (NN - 1) / 2;
  int pair_a[NP], pair_b[NP];
  for (int a = 0, p = 0; a < NN; ++a) {
    for (int b = a + 1; b < NN; ++b, ++p) pair_a[p] = a, pair_b[p] = b;
  }
  const at::ScalarType type = elements.scalar_type();
  const int64_t num_rows = rows.size(0), num_elements = elements.size(0), num_nodes = incidences.size(0);
  const int64_t num_edges = edges.size(0), edge_list_slots = edge_slots.size(0), num_model = removed.size(0);
  const int64_t num_slots = node_items.size(0), sink = num_slots - 1;
  I* el = elements.data_ptr<I>();
  I* ed = edges.data_ptr<I>();
  I* ee = element_edges.data_ptr<I>();
  const I* inc = incidences.data_ptr<I>();
  const I* nd = nodes.data_ptr<I>();
  const I* row = rows.data_ptr<I>();
  const int64_t* id = ids.data_ptr<int64_t>();
  const bool* gone = removed.data_ptr<bool>();
  std::vector<I> old_rows;
  const Changes c = changed_entries<I, NN>(el, num_elements, num_nodes, row, id, nd, num_rows, old_rows);

  // 1. the plan: the pairs whose edge changes (a node of theirs does), in row-major order, the key
  // of their new edge (lower node V + higher node) and their old edge
  std::vector<int64_t> pair_entry, pair_key, pair_old_edge, pair_id;
  {
    bool moved_node[NN];
    size_t k = 0;
    for (int64_t m = 0; m < num_rows; ++m) {
      std::fill(moved_node, moved_node + NN, false);
      for (; k < c.entry.size() && c.entry[k] / NN == m; ++k) moved_node[c.entry[k] % NN] = true;
      const int64_t r = row[m];
      for (int p = 0; p < NP; ++p) {
        if (!moved_node[pair_a[p]] && !moved_node[pair_b[p]]) continue;
        const int64_t a = nd[m * NN + pair_a[p]], b = nd[m * NN + pair_b[p]];
        const int64_t old_edge = ee[r * NP + p];
        TORCH_CHECK(old_edge >= 0 && old_edge < edge_rows_used, "tensormass: element_edges: row ", std::to_string(r),
                    " holds edge ", std::to_string(old_edge), ", outside the ", std::to_string(edge_rows_used),
                    " edge rows in use (edge_rows_used)");
        pair_entry.push_back(m * NP + p);
        pair_key.push_back(std::min(a, b) * num_nodes + std::max(a, b));
        pair_old_edge.push_back(old_edge);
        pair_id.push_back(id[m]);
      }
    }
  }
  // the new edges: the keys sorted and unique; each moved pair's among them
  std::vector<int64_t> new_keys, edge_of(pair_key.size());
  {
    std::vector<std::pair<int64_t, int64_t>> keyed(pair_key.size());  // (key, pair)
    for (size_t k = 0; k < pair_key.size(); ++k) keyed[k] = {pair_key[k], static_cast<int64_t>(k)};
    sort_by_key(keyed, num_nodes * num_nodes, [](const std::pair<int64_t, int64_t>& p) { return p.first; });
    for (const auto& p : keyed) {
      if (new_keys.empty() || new_keys.back() != p.first) new_keys.push_back(p.first);
      edge_of[p.second] = static_cast<int64_t>(new_keys.size()) - 1;
    }
  }
  const int64_t count = static_cast<int64_t>(new_keys.size());
  // the old edges the moved pairs leave (sorted), and those no alive element is left on: as many
  // alive elements listed as pairs leaving
  std::vector<int64_t> leaving(pair_old_edge), left, dead;
  sort_by_key(leaving, edge_rows_used, [](int64_t e) { return e; });
  std::vector<int64_t> moving;
  for (size_t begin = 0; begin < leaving.size();) {
    size_t end = begin;
    while (end < leaving.size() && leaving[end] == leaving[begin]) ++end;
    left.push_back(leaving[begin]);
    moving.push_back(static_cast<int64_t>(end - begin));
    begin = end;
  }
  ListColumns<I> edge_lists(edge_slots.data_ptr<I>(), edge_list_slots, num_edges);
  edge_lists.load(left);
  for (size_t e = 0; e < left.size(); ++e) {
    const I* list = edge_lists.list(left[e]);
    int64_t alive = 0;
    for (int64_t s = 0; s < edge_list_slots; ++s) {
      const int64_t listed = list[s];
      if (listed < 0) continue;
      TORCH_CHECK(listed < num_model, "tensormass: edge_slots lists element ", std::to_string(listed),
                  ", outside the ", std::to_string(num_model), " of removed");
      alive += !gone[listed];
    }
    if (alive == moving[e]) dead.push_back(left[e]);
  }
  // the room: each node's edges after the cut (+1 per end of a new edge, -1 per end of an emptied
  // one), the most of any node against the plan's slots but its sink
  std::vector<std::pair<int64_t, int64_t>> change;
  change.reserve(2 * (new_keys.size() + dead.size()));
  for (const int64_t key : new_keys) change.emplace_back(key / num_nodes, 1), change.emplace_back(key % num_nodes, 1);
  for (const int64_t edge : dead) {
    for (int end = 0; end < 2; ++end) {
      const int64_t node = ed[edge * 2 + end];
      TORCH_CHECK(node >= 0 && node < num_nodes, "tensormass: edges: edge ", std::to_string(edge), " holds node ",
                  std::to_string(node), ", outside the ", std::to_string(num_nodes), " nodes of incidences");
      change.emplace_back(node, -1);
    }
  }
  sort_by_key(change, num_nodes, [](const std::pair<int64_t, int64_t>& n) { return n.first; });
  int64_t need = 0;
  if (num_nodes > 0) {
    need = std::numeric_limits<int64_t>::min();
    int64_t v = 0;
    for (size_t k = 0; k <= change.size();) {
      const int64_t next = k < change.size() ? change[k].first : num_nodes;
      for (; v < next; ++v) need = std::max<int64_t>(need, inc[v]);
      if (k == change.size()) break;
      int64_t delta = 0;
      for (; k < change.size() && change[k].first == next; ++k) delta += change[k].second;
      need = std::max<int64_t>(need, static_cast<int64_t>(inc[next]) + delta);
      v = next + 1;
    }
  }
  const int64_t first_new = edge_rows_used;
  if (need > sink || first_new + count > num_edges) {
    return unedited(status_tensor(need, count, false), type, edge_list_slots, NP, node_slots.size(0), NN);
  }

  // the edits, in workspaces: the model's lists
  const std::vector<int64_t> nodes_changed = changed_nodes(c, num_nodes);
  ListColumns<I> model_lists(node_slots.data_ptr<I>(), node_slots.size(0), num_nodes);
  model_lists.load(nodes_changed);
  edit_node_lists(model_lists, c.old_node, c.new_node, c.id);
  // the edges' lists: the moved elements leave their old edges and are listed on the new ones
  // (the pool's first rows) in the order of the pairs, their ids ascending
  remove_from_lists(edge_lists, pair_old_edge, pair_id, "edge_slots");
  std::vector<int64_t> new_rows(count);
  std::iota(new_rows.begin(), new_rows.end(), first_new);
  edge_lists.load(new_rows);
  {
    std::vector<int64_t> listed(count, 0);
    for (size_t k = 0; k < edge_of.size(); ++k) {
      const int64_t j = edge_of[k], slot = listed[j]++;
      TORCH_CHECK(slot < edge_list_slots, "tensormass: edge_slots has ", std::to_string(edge_list_slots),
                  " slots but new edge ", std::to_string(first_new + j), " would list ", std::to_string(slot + 1),
                  " elements");
      edge_lists.list(first_new + j)[slot] = static_cast<I>(pair_id[k]);
    }
  }
  // the plan's lists: the emptied edges' items leave their nodes, the new edges' join theirs
  PlanLists<I> plan(node_items.data_ptr<I>(), num_slots, num_nodes, inc, force_index.numel());
  std::vector<int64_t> dead_items, dead_ends, new_items(2 * count), new_ends(2 * count);
  for (const int64_t edge : dead) {
    for (int end = 0; end < 2; ++end) dead_items.push_back(edge * 2 + end), dead_ends.push_back(ed[edge * 2 + end]);
  }
  for (int64_t j = 0; j < count; ++j) {
    new_items[2 * j] = 2 * (first_new + j), new_items[2 * j + 1] = 2 * (first_new + j) + 1;
    new_ends[2 * j] = new_keys[j] / num_nodes, new_ends[2 * j + 1] = new_keys[j] % num_nodes;
  }
  std::vector<int64_t> ends_changed(dead_ends);
  ends_changed.insert(ends_changed.end(), new_ends.begin(), new_ends.end());
  sort_unique(ends_changed, num_nodes);
  plan.items.load(ends_changed);
  std::vector<int64_t> items_changed = edit_plan_lists(plan, dead_items, dead_ends, new_items, new_ends);
  // the rows whose edges are summed again: the cut's, and for each old edge left that keeps an
  // alive element, the first such element listed (its row names the edge)
  std::vector<int64_t> refresh_rows(row, row + num_rows);
  const I* row_of = element_row.data_ptr<I>();
  for (const int64_t edge : left) {
    const I* list = edge_lists.list(edge);
    for (int64_t s = 0; s < edge_list_slots; ++s) {
      const int64_t listed = list[s];
      if (listed < 0 || gone[listed]) continue;  // listed < num_model: checked above
      const int64_t r = row_of[listed];
      TORCH_CHECK(r >= 0 && r < num_elements, "tensormass: element_row holds row ", std::to_string(r),
                  ", outside the ", std::to_string(num_elements), " elements");
      refresh_rows.push_back(r);
      break;
    }
  }
  sort_unique(refresh_rows, num_elements);
  items_changed.insert(items_changed.end(), dead_items.begin(), dead_items.end());
  sort_unique(items_changed, 2 * num_edges);

  // 2. the writes (the edges' in the reference's order: the new rows, then the emptied ones
  // zeroed, a zero edge (0, 0) in node 0's sink slot)
  model_lists.write();
  edge_lists.write();
  I* fi = force_index.data_ptr<I>();
  plan.write(fi, incidences.data_ptr<I>());
  for (int64_t j = 0; j < count; ++j) {
    ed[2 * (first_new + j)] = static_cast<I>(new_keys[j] / num_nodes);
    ed[2 * (first_new + j) + 1] = static_cast<I>(new_keys[j] % num_nodes);
  }
  for (const int64_t edge : dead) {
    ed[2 * edge] = ed[2 * edge + 1] = 0;
    fi[2 * edge] = fi[2 * edge + 1] = static_cast<I>(sink);
  }
  for (size_t k = 0; k < pair_entry.size(); ++k) {
    ee[static_cast<int64_t>(row[pair_entry[k] / NP]) * NP + pair_entry[k] % NP] = static_cast<I>(first_new + edge_of[k]);
  }
  for (int64_t m = 0; m < num_rows; ++m) std::copy(nd + m * NN, nd + (m + 1) * NN, el + static_cast<int64_t>(row[m]) * NN);

  // 3. the results: the edges the node graphs take again (those whose slots moved and those
  // summed again), the changed columns and rows as the tables hold them now
  std::vector<int64_t> graph_edges;
  graph_edges.reserve(items_changed.size() + refresh_rows.size() * NP);
  for (const int64_t item : items_changed) graph_edges.push_back(item / 2);
  for (const int64_t r : refresh_rows) {
    for (int p = 0; p < NP; ++p) {
      const int64_t edge = ee[r * NP + p];
      TORCH_CHECK(edge >= 0 && edge < num_edges, "tensormass: element_edges: row ", std::to_string(r), " holds edge ",
                  std::to_string(edge), ", outside the ", std::to_string(num_edges), " edges");
      graph_edges.push_back(edge);
    }
  }
  sort_unique(graph_edges, num_edges);
  std::vector<int64_t> slot_edges(left), edge_rows(new_rows);
  slot_edges.insert(slot_edges.end(), new_rows.begin(), new_rows.end());
  edge_rows.insert(edge_rows.end(), dead.begin(), dead.end());
  at::Tensor edge_values = at::empty({static_cast<int64_t>(edge_rows.size()), 2}, at::TensorOptions().dtype(type));
  for (size_t i = 0; i < edge_rows.size(); ++i) {
    edge_values.data_ptr<I>()[2 * i] = ed[2 * edge_rows[i]];
    edge_values.data_ptr<I>()[2 * i + 1] = ed[2 * edge_rows[i] + 1];
  }
  at::Tensor row_edges = at::empty({num_rows, NP}, at::TensorOptions().dtype(type));
  for (int64_t m = 0; m < num_rows; ++m) {
    const I* from = ee + static_cast<int64_t>(row[m]) * NP;
    std::copy(from, from + NP, row_edges.data_ptr<I>() + m * NP);
  }
  return {status_tensor(need, count, true),
          index_tensor<I>(refresh_rows, type),
          index_tensor<I>(dead, at::kLong),
          index_tensor<I>(graph_edges, type),
          index_tensor<I>(ends_changed, at::kLong),
          gathered<I>(incidences.data_ptr<I>(), ends_changed, type),
          index_tensor<I>(items_changed, at::kLong),
          gathered<I>(fi, items_changed, type),
          index_tensor<I>(slot_edges, at::kLong),
          edge_lists.columns(slot_edges, type),
          index_tensor<I>(edge_rows, at::kLong),
          edge_values,
          row_edges,
          index_tensor<I>(nodes_changed, at::kLong),
          model_lists.columns(nodes_changed, type),
          both_rows<I, NN>(old_rows, nd, num_rows, type)};
}

}  // namespace cutting

// ---------------------------------------------------------------------------------------------
// Argument checks and dispatch
// ---------------------------------------------------------------------------------------------

// A host index table of the elements' index type and the given shape.
inline void check_table(const at::Tensor& t, const char* name, at::ScalarType index_type, at::IntArrayRef shape,
                        const char* op) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device().is_cpu(), "tensormass: ", name, " is on ", t.device().str(), "; ", op,
              " runs on the CPU (edit host copies of the tables)");
  TORCH_CHECK(t.scalar_type() == index_type, "tensormass: ", name, " is ", dtype_str(t.scalar_type()), "; expected ",
              dtype_str(index_type), " (index tensors must all be int32 or all int64, as elements)");
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", shape_str(t.sizes()), "; expected ",
              shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

// What both ops take: the elements, the plan (its lists over the incidences' V nodes), the model's
// lists over the same nodes and the re-pointed rows.
inline at::ScalarType check_cut_tables(const at::Tensor& elements, const at::Tensor& force_index,
                                       const at::Tensor& incidences, const at::Tensor& node_items,
                                       const at::Tensor& node_slots, const at::Tensor& rows, const at::Tensor& ids,
                                       const at::Tensor& nodes, int64_t item_width, const char* op) {
  const at::ScalarType index_type = index_type_of(elements, "elements");
  TORCH_CHECK(elements.dim() == 2 && (elements.size(1) == 4 || elements.size(1) == 3),
              "tensormass: elements must be [N, 4] (tetrahedra) or [N, 3] (triangles), got shape ",
              shape_str(elements.sizes()));
  check_table(elements, "elements", index_type, elements.sizes(), op);
  const int64_t n = elements.size(1);
  TORCH_CHECK(incidences.dim() == 1, "tensormass: incidences must be [V], got shape ", shape_str(incidences.sizes()));
  check_table(incidences, "incidences", index_type, incidences.sizes(), op);
  const int64_t num_nodes = incidences.size(0);
  TORCH_CHECK(force_index.dim() == 2 && force_index.size(1) == (item_width ? item_width : n),
              "tensormass: force_index must be [items, ", std::to_string(item_width ? item_width : n), "], got shape ",
              shape_str(force_index.sizes()));
  check_table(force_index, "force_index", index_type, force_index.sizes(), op);
  TORCH_CHECK(node_items.dim() == 2, "tensormass: node_items must be [S, V], got shape ", shape_str(node_items.sizes()));
  check_table(node_items, "node_items", index_type, {node_items.size(0), num_nodes}, op);
  TORCH_CHECK(node_slots.dim() == 2, "tensormass: node_slots must be [S, V], got shape ", shape_str(node_slots.sizes()));
  check_table(node_slots, "node_slots", index_type, {node_slots.size(0), num_nodes}, op);
  TORCH_CHECK(rows.dim() == 1, "tensormass: rows must be [M], got shape ", shape_str(rows.sizes()));
  check_table(rows, "rows", index_type, rows.sizes(), op);
  const int64_t num_rows = rows.size(0);
  check_table(ids, "ids", at::kLong, {num_rows}, op);
  check_table(nodes, "nodes", index_type, {num_rows, n}, op);
  return index_type;
}

// cutting_edit_element_tables: see schema.cpp.
inline cutting::ElementTablesResult cutting_edit_element_tables(at::Tensor elements, at::Tensor force_index,
                                                                at::Tensor incidences, at::Tensor node_items,
                                                                at::Tensor node_slots, const at::Tensor& rows,
                                                                const at::Tensor& ids, const at::Tensor& nodes) {
  constexpr const char* op = "cutting_edit_element_tables";
  const at::ScalarType index_type =
      check_cut_tables(elements, force_index, incidences, node_items, node_slots, rows, ids, nodes, 0, op);
  TORCH_CHECK(force_index.size(0) == elements.size(0), "tensormass: force_index has shape ",
              shape_str(force_index.sizes()), "; expected the shape of elements, ", shape_str(elements.sizes()));
  cutting::ElementTablesResult result;
  dispatch_index(index_type, [&](auto i_tag) {
    using I = decltype(i_tag);
    if (elements.size(1) == 4) {
      result = cutting::edit_element_tables<I, 4>(elements, force_index, incidences, node_items, node_slots, rows, ids,
                                                  nodes);
    } else {
      result = cutting::edit_element_tables<I, 3>(elements, force_index, incidences, node_items, node_slots, rows, ids,
                                                  nodes);
    }
  });
  return result;
}

// cutting_edit_edge_tables: see schema.cpp.
inline cutting::EdgeTablesResult cutting_edit_edge_tables(at::Tensor elements, at::Tensor force_index,
                                                          at::Tensor incidences, at::Tensor node_items,
                                                          at::Tensor node_slots, at::Tensor edges, at::Tensor edge_slots,
                                                          at::Tensor element_edges, const at::Tensor& rows,
                                                          const at::Tensor& ids, const at::Tensor& nodes,
                                                          const at::Tensor& element_row, const at::Tensor& removed,
                                                          int64_t edge_rows_used) {
  constexpr const char* op = "cutting_edit_edge_tables";
  const at::ScalarType index_type =
      check_cut_tables(elements, force_index, incidences, node_items, node_slots, rows, ids, nodes, 2, op);
  const int64_t n = elements.size(1), num_edges = force_index.size(0);
  check_table(edges, "edges", index_type, {num_edges, 2}, op);
  TORCH_CHECK(edge_slots.dim() == 2, "tensormass: edge_slots must be [S, Ed], got shape ",
              shape_str(edge_slots.sizes()));
  check_table(edge_slots, "edge_slots", index_type, {edge_slots.size(0), num_edges}, op);
  check_table(element_edges, "element_edges", index_type, {elements.size(0), n * (n - 1) / 2}, op);
  TORCH_CHECK(element_row.dim() == 1, "tensormass: element_row must be [N_model], got shape ",
              shape_str(element_row.sizes()));
  check_table(element_row, "element_row", index_type, element_row.sizes(), op);
  TORCH_CHECK(removed.defined() && removed.device().is_cpu() && removed.scalar_type() == at::kBool &&
                  removed.dim() == 1 && removed.is_contiguous(),
              "tensormass: removed must be a contiguous [N_model] bool tensor on the CPU");
  TORCH_CHECK(removed.size(0) == element_row.size(0), "tensormass: removed has shape ", shape_str(removed.sizes()),
              "; expected [", std::to_string(element_row.size(0)), "] (element_row is [N_model])");
  TORCH_CHECK(edge_rows_used >= 0 && edge_rows_used <= num_edges, "tensormass: edge_rows_used is ",
              std::to_string(edge_rows_used), ", outside 0 .. ", std::to_string(num_edges), " (the rows of edges)");
  cutting::EdgeTablesResult result;
  dispatch_index(index_type, [&](auto i_tag) {
    using I = decltype(i_tag);
    if (n == 4) {
      result = cutting::edit_edge_tables<I, 4>(elements, force_index, incidences, node_items, node_slots, edges,
                                               edge_slots, element_edges, rows, ids, nodes, element_row, removed,
                                               edge_rows_used);
    } else {
      result = cutting::edit_edge_tables<I, 3>(elements, force_index, incidences, node_items, node_slots, edges,
                                               edge_slots, element_edges, rows, ids, nodes, element_row, removed,
                                               edge_rows_used);
    }
  });
  return result;
}

}  // namespace tensormass
